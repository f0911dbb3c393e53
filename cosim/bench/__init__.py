"""`cosim bench`: benchmarks that state the hardware and the settings with their numbers.

- ``mpm``: MPM throughput (particle-substeps per second), backward/forward cost, peak memory;
- ``contact``: the paper's contact benchmark (penetration, rebound, time per contact model);
- ``coupling``: what the MPM-DART coupling costs on pour_water and pull_door;
- ``cloth``: the cloth step, the nearest-face query, the MPM-cloth coupling and a taco-sized case;
- ``fuzz``: random valid scenes run to an outcome each (ran, or a clear scene or simulation error);
- ``accuracy``: run time against error on reference problems (work-precision diagrams, Pareto fronts);
- ``long``: one shipped scene of each type for 10,000 macro steps under the runner's guards (energy, volume).

Each writes ``OUT/<name>.csv`` (cloth: ``OUT/cloth.json``, its results being nested; fuzz: also
``OUT/repros/seed_N.yaml`` for each failure; accuracy: also a PNG per problem) and ``OUT/<name>.md``, a report
that starts with the command line, the date, the hardware and the commit (``cosim.bench.report``); docs/benchmarks.md
keeps the latest of each. The modules import Taichi only when run, so this package is cheap to import.
"""

from __future__ import annotations

from pathlib import Path

BENCHMARKS = ("mpm", "contact", "coupling", "cloth", "fuzz", "accuracy", "long")


def run_bench(
    what: str,
    out_dir: Path,
    quick: bool = False,
    repeat: int = 3,
    workers: int | None = None,
    address: str | None = None,
    count: int = 200,
    seed: int = 0,
    steps: int = 10_000,
    scenes: list[str] | None = None,
    sizes: bool = False,
    baseline: Path | None = None,
    profile: bool = False,
    arch: str = "cpu",
    threads: list[int] | None = None,
    scatters: list[str] | None = None,
    particles: int | None = None,
    peer: str | None = None,
) -> int:
    """Run benchmark ``what`` (one of ``BENCHMARKS``), writing into ``out_dir``; returns the exit code.

    ``quick``: fewer steps (a smoke run); ``repeat`` (contact, coupling, cloth): repetitions, times are medians;
    ``workers`` / ``address`` (contact, accuracy: their independent runs): on Ray (``cosim.scale.pool``) when more than one;
    ``count`` / ``seed`` (fuzz): how many random scenes, from which seed (``workers``: its processes);
    ``steps`` / ``scenes`` (long): macro steps per scene, which shipped scenes (default one of each type);
    ``sizes`` / ``baseline`` / ``profile`` (mpm): 10k-1M particles; current/baseline ratios against the
    cosim in that folder (``repeat`` runs each); Taichi's kernel profile (also of contact's grid run); ``arch``, ``threads``, ``scatters``,
    ``particles``: on the GPU (``arch`` also for contact), on each CPU thread count, with each scatter, one block of that size
    (``cosim.bench.mpm``); ``peer`` ("softmac=DIR"): current/peer ratios against SoftMAC's MPM in DIR
    (``cosim.bench.mpm_peer``).
    """
    mpm_only = sizes or baseline is not None or threads or scatters or particles or peer
    from cosim.errors import InputError

    if what != "mpm" and mpm_only:
        raise InputError(
            "--sizes, --baseline, --peer, --threads, --scatter and --particles are options of "
            f"`bench mpm`, not of `bench {what}`"
        )
    if what not in ("mpm", "contact") and profile:
        raise InputError(f"--profile is an option of `bench mpm` and `bench contact`, not of `bench {what}`")
    if what not in ("mpm", "contact") and arch != "cpu":
        raise InputError(f"--arch is an option of `bench mpm` and `bench contact`, not of `bench {what}`")
    from cosim.bench.report import bench_command

    command = bench_command(
        what, out=out_dir, quick=quick, repeat=repeat, sizes=sizes, baseline=baseline, profile=profile, count=count,
        seed=seed, steps=steps, scene=scenes, workers=workers, address=address, arch=arch, particles=particles, peer=peer,
        threads=",".join(map(str, threads)) if threads else None, scatter=",".join(scatters) if scatters else None,
    )  # fmt: skip
    if what == "long":
        from cosim.bench.long_runs import run_long_bench

        return run_long_bench(
            out_dir, steps=steps, quick=quick, workers=workers, address=address, scenes=scenes, command=command
        )
    if what == "fuzz":
        from cosim.bench.fuzz import run_fuzz_bench
        from cosim.errors import InputError

        if address:
            raise InputError("bench fuzz runs on this machine's processes (--workers); --address is not supported")
        return run_fuzz_bench(out_dir, count=count, seed=seed, workers=workers, command=command)
    if what == "accuracy":
        from cosim.bench.accuracy import run_accuracy_bench

        return run_accuracy_bench(out_dir, quick=quick, workers=workers, address=address, command=command)
    if what == "cloth":
        from cosim.bench.cloth import run_cloth_bench

        return run_cloth_bench(out_dir, quick=quick, repeat=repeat, command=command)
    if what == "coupling":
        from cosim.bench.coupling import run_coupling_bench

        return run_coupling_bench(out_dir, quick=quick, repeat=repeat, command=command)
    if what == "contact" and profile:
        from cosim.bench.contact_profile import run_contact_profile

        return run_contact_profile(out_dir, quick=quick, arch=arch, command=command)
    if what == "contact":
        from cosim.bench.contact import run_contact_bench

        return run_contact_bench(
            out_dir, quick=quick, repeat=repeat, workers=workers, address=address, command=command, arch=arch
        )
    if what == "mpm":
        from cosim.bench.mpm_modes import run_mpm_bench

        return run_mpm_bench(
            out_dir, quick=quick, sizes=sizes, baseline=baseline, repeat=repeat, profile=profile, command=command,
            arch=arch, threads=threads, scatters=scatters, particles=particles, peer=peer,
        )  # fmt: skip
    raise ValueError(f"unknown benchmark {what!r}; choose one of {BENCHMARKS}")
