"""`cosim bench`: benchmarks that state the hardware and the settings with their numbers.

- ``mpm``: MPM throughput (particle-substeps per second), backward/forward cost, peak memory;
- ``contact``: the paper's contact benchmark (penetration, rebound, time per contact model);
- ``coupling``: what the MPM-DART coupling costs on pour_water and pull_door;
- ``cloth``: the cloth step, the nearest-face query, the MPM-cloth coupling and a taco-sized case.

Each writes ``OUT/<name>.csv`` (cloth: ``OUT/cloth.json``, its results being nested). The modules import Taichi only when run, so this package is cheap to import.
"""

from __future__ import annotations

from pathlib import Path

BENCHMARKS = ("mpm", "contact", "coupling", "cloth")


def run_bench(
    what: str,
    out_dir: Path,
    quick: bool = False,
    repeat: int = 3,
    workers: int | None = None,
    address: str | None = None,
) -> int:
    """Run benchmark ``what`` (one of ``BENCHMARKS``), writing into ``out_dir``; returns the exit code.

    ``quick``: fewer steps (a smoke run); ``repeat`` (contact, coupling, cloth): repetitions, times are medians;
    ``workers`` / ``address`` (contact: its independent runs): on Ray (``cosim.scale.pool``) when more than one.
    """
    if what == "cloth":
        from cosim.bench.cloth import run_cloth_bench

        return run_cloth_bench(out_dir, quick=quick, repeat=repeat)
    if what == "coupling":
        from cosim.bench.coupling import run_coupling_bench

        return run_coupling_bench(out_dir, quick=quick, repeat=repeat)
    if what == "contact":
        from cosim.bench.contact import run_contact_bench

        return run_contact_bench(out_dir, quick=quick, repeat=repeat, workers=workers, address=address)
    if what == "mpm":
        from cosim.bench.mpm import run_mpm_bench

        return run_mpm_bench(out_dir, quick=quick)
    raise ValueError(f"unknown benchmark {what!r}; choose one of {BENCHMARKS}")
