"""`cosim bench mpm`'s modes (``cosim.bench.mpm``: throughput, sizes, profile;
``cosim.bench.mpm_baseline``: against another checkout), chosen from the command's flags."""

from __future__ import annotations

import sys
from pathlib import Path

from cosim.bench.mpm import GUARDS_OFF, fixed_configs, run_profile, run_throughput, size_configs
from cosim.bench.mpm_baseline import run_baseline_bench
from cosim.guards import announce


def run_mpm_bench(
    out_dir: Path, quick: bool = False, sizes: bool = False, baseline: Path | None = None, repeat: int = 3,
    profile: bool = False, command: str | None = None,
) -> int:  # fmt: skip
    """``cosim bench mpm``: the chosen mode (module docstring) into ``out_dir``; returns the exit code."""
    if profile and (sizes or baseline is not None):
        from cosim.errors import InputError

        raise InputError("--profile runs alone (3D 64³ float32); leave out --sizes and --baseline")
    announce(GUARDS_OFF)
    out_dir.mkdir(parents=True, exist_ok=True)
    configs = size_configs(quick) if sizes else fixed_configs(quick)
    try:
        if profile:
            return run_profile(out_dir, command=command)
        if baseline is not None:
            return run_baseline_bench(out_dir, configs, baseline, repeat, "mpm_sizes" if sizes else "mpm", command)
        return run_throughput(out_dir, configs, "mpm_sizes" if sizes else "mpm", command)
    except RuntimeError as err:
        print(err, file=sys.stderr)
        return 1
