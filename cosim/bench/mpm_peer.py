"""`cosim bench mpm --peer softmac=DIR`: cosim's MPM against SoftMAC's, in one run on one machine.

DIR is a checkout of SoftMAC (``git clone https://github.com/damianliumin/SoftMAC DIR``); its engine
runs in its own processes through ``mpm_measure_softmac.py``, alternating with cosim's runs as a
baseline does (``cosim.bench.mpm_baseline.run_comparison``), on the configurations both engines can
run: a 3D float64 elastic block (``PEER_CONFIGS``; SoftMAC asserts float64).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from cosim.bench.mpm import Interpreter, current_interpreter
from cosim.bench.mpm_baseline import run_comparison
from cosim.errors import InputError

PEERS = {"softmac": ("softmac/engine/mpm_simulator.py", "https://github.com/damianliumin/SoftMAC")}
MEASURE_SOFTMAC = Path(__file__).with_name("mpm_measure_softmac.py")
# 30k particles on 64³, float64 (the CPU's 3D comparison and the GPU's small scene): one size, since
# SoftMAC's kernels are compiled for their fields' shapes, and its first 3D backward compiles for minutes
PEER_CONFIGS = [{"dim": 3, "cells": 64, "side": 31, "precision": "float64", "substeps": 10, "macro_steps": 10}]


def peer_configs(quick: bool = False) -> list[dict]:
    """The configurations of a peer comparison (``--quick``: 5 x 2 steps)."""
    if quick:
        return [{**c, "substeps": 5, "macro_steps": 2} for c in PEER_CONFIGS]
    return [dict(c) for c in PEER_CONFIGS]


def peer_interpreter(spec: str) -> Interpreter:
    """The interpreter that runs the peer ``spec`` ("softmac=DIR"); an InputError naming what is wrong."""
    name, _, folder = spec.partition("=")
    if name not in PEERS or not folder:
        raise InputError(f"--peer {spec}: give NAME=DIR with NAME one of {', '.join(PEERS)}")
    module, url = PEERS[name]
    root = Path(folder).expanduser().resolve()
    if not (root / module).exists():
        raise InputError(f"--peer {spec}: no {module} under {root}; clone {url} there")
    # the peer's checkout, then this cosim (its measurement helpers), then what this process was given
    path = os.pathsep.join([str(root), str(current_interpreter().root), *filter(None, [os.environ.get("PYTHONPATH")])])
    env = dict(os.environ, PYTHONPATH=path)
    return Interpreter(sys.executable, root, env, label=name, measure=MEASURE_SOFTMAC, package=name)


def run_peer_bench(
    out_dir: Path, configs: list[dict], spec: str, repeat: int, name: str, command: str | None = None
) -> int:
    """Measure ``configs`` with the peer ``spec`` and with this cosim, interleaved (``run_comparison``)."""
    peer = peer_interpreter(spec)
    print(f"peer: {peer.label} from {peer.root}; current: {current_interpreter().root}")
    return run_comparison(out_dir, configs, peer, peer.label, repeat, f"{name}_{peer.label}", command)
