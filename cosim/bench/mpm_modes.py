"""`cosim bench mpm`'s modes (``cosim.bench.mpm``: throughput, sizes, GPU, thread curve, profile;
``cosim.bench.mpm_baseline``: against another checkout), chosen from the command's flags."""

from __future__ import annotations

import sys
from pathlib import Path

from cosim.bench.mpm import (
    GUARDS_OFF,
    expand,
    fixed_configs,
    gpu_configs,
    particle_config,
    run_profile,
    run_throughput,
    size_configs,
)
from cosim.bench.mpm_baseline import run_baseline_bench
from cosim.bench.mpm_peer import peer_configs, run_peer_bench
from cosim.engines.arch import SCATTERS
from cosim.errors import InputError
from cosim.guards import announce


def run_mpm_bench(
    out_dir: Path, quick: bool = False, sizes: bool = False, baseline: Path | None = None, repeat: int = 3,
    profile: bool = False, command: str | None = None, arch: str = "cpu", threads: list[int] | None = None,
    scatters: list[str] | None = None, particles: int | None = None, peer: str | None = None,
) -> int:  # fmt: skip
    """``cosim bench mpm``: the chosen mode (module docstring) into ``out_dir``; returns the exit code."""
    check_mode(sizes, baseline, profile, arch, threads, scatters, particles, peer)
    announce(GUARDS_OFF)
    out_dir.mkdir(parents=True, exist_ok=True)
    if peer:
        configs, name = peer_configs(quick), "mpm"
    elif particles:
        configs, name = [particle_config(particles, quick)], "mpm_particles"
    elif sizes:
        configs, name = size_configs(quick), "mpm_sizes"
    else:
        configs, name = gpu_configs(quick) if arch != "cpu" else fixed_configs(quick), "mpm"
    name += "" if arch == "cpu" else f"_{arch}"
    name += "_threads" if threads else ""
    configs = expand(configs, arch, threads, scatters)
    try:
        if profile:
            return run_profile(out_dir, profile_config(arch, particles, quick), command=command)
        if baseline is not None:
            return run_baseline_bench(out_dir, configs, baseline, repeat, name, command)
        if peer:
            return run_peer_bench(out_dir, configs, peer, repeat, name, command)
        return run_throughput(out_dir, configs, name, command)
    except RuntimeError as err:
        print(err, file=sys.stderr)
        return 1


def profile_config(arch: str, particles: int | None, quick: bool) -> dict | None:
    """What ``--profile`` profiles: the block of ``--particles``, else on a GPU the 2M block of
    ``GPU_CONFIGS`` (10 x 3 steps), else None (``run_profile``'s 3D 64³ float32 on the CPU)."""
    if particles:
        return {**particle_config(particles, quick), "arch": arch}
    if arch != "cpu":
        return gpu_configs(quick)[-1] | {"arch": arch}
    return None


def check_mode(
    sizes: bool, baseline: Path | None, profile: bool, arch: str, threads: list[int] | None,
    scatters: list[str] | None, particles: int | None, peer: str | None = None,
) -> None:  # fmt: skip
    """An InputError naming the flags that do not go together, or a scatter that does not exist."""
    if peer and (sizes or baseline is not None or profile or threads or scatters or particles):
        raise InputError("--peer compares its own sizes on the default settings; give it with --arch, --repeat only")
    if profile and (sizes or baseline is not None or threads or scatters):
        raise InputError(
            "--profile profiles one configuration (3D 64³ float32 on the CPU, the 2M block with --arch cuda, or "
            "--particles N); leave out --sizes, --baseline, --threads and --scatter"
        )
    if threads and arch != "cpu":
        raise InputError(f"--threads sets CPU threads; --arch {arch} has none to set: leave one out")
    if sizes and particles:
        raise InputError("--sizes and --particles both choose the sizes: give one")
    unknown = sorted(set(scatters or ()) - set(SCATTERS))
    if unknown:
        raise InputError(f"--scatter {','.join(unknown)}: choose from {', '.join(SCATTERS)}")
