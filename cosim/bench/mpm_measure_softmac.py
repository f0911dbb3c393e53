"""SoftMAC's MPM measured as ``mpm_measure`` measures cosim's: the peer of `cosim bench mpm --peer softmac=DIR`.

DIR is a checkout of SoftMAC (github.com/damianliumin/SoftMAC, the paper's code), on PYTHONPATH with
the cosim: its ``softmac.engine.mpm_simulator.MPMSimulator`` is imported and run as it is (it needs
only taichi and numpy), never copied. Same block of particles (``block_points``), dt, substeps and
macro steps as cosim's rows; Taichi started as SoftMAC's own environment starts it (``fast_math``,
9 GB of device memory on a GPU).

What its engine allows: 3D and float64 only (it asserts float64); a grid of 128 x quality / 2 cells a
side in 3D (quality = cells / 64); an elastic corotated body (its ``ptype`` 1, whose Lame parameters
it scales by 0.3) of its default E 5e3 Pa, nu 0.2 and density 1 (its ``p_rho``); the domain's walls,
no contact. It keeps every substep's particle state (``max_steps`` frames), so its forward is always
the recorded one; the backward runs its ``substep_grad`` over the frames in reverse, seeded with
dL/dx = 1 on the last frame. Reported per macro step as ``mpm_measure``: medians of the forward and
of the backward, compile excluded (a first macro step of each, then the run again from the start).
"""

import json
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

GRAVITY = (0.0, -9.81, 0.0)


def _config(n_particles: int, cells: int, frames: int) -> SimpleNamespace:
    """SoftMAC's simulator settings (the keys its ``MPMSimulator`` reads from its yacs config)."""
    return SimpleNamespace(
        dim=3,
        quality=cells / 64,
        yield_stress=50.0,
        dtype="float64",
        max_steps=frames,
        n_particles=n_particles,
        E=5e3,
        nu=0.2,
        ground_friction=0.0,
        gravity=GRAVITY,
        ptype=1,  # elastic
        material_model=0,  # fixed corotated
        dt=1e-4,
        n_controllers=0,
        collision_type=0,  # grid (no primitives: only the walls)
    )


def measure(
    dim: int,
    cells: int,
    side: int,
    precision: str,
    substeps: int,
    macro_steps: int,
    arch: str = "cpu",
    profile: bool = False,
    scatter: str | None = None,
) -> dict:
    """One configuration of SoftMAC's engine; the row ``mpm_measure.measure`` returns for cosim's."""
    import taichi as ti

    from cosim.bench.mpm_measure import DT, _peak_mib, _timed, block_points, result_row
    from cosim.errors import InputError

    if dim != 3 or precision != "float64" or profile or scatter:
        raise InputError("SoftMAC's engine runs 3D float64 only, without a profile or a scatter choice")
    if arch == "cuda":
        ti.init(arch=ti.cuda, debug=False, fast_math=True, device_memory_GB=9)
    else:
        ti.init(arch=ti.cpu, debug=False, fast_math=True)
    import softmac.engine.mpm_simulator as softmac_mpm

    base = _peak_mib()
    pts = block_points(dim, cells, side)
    n, total = len(pts), substeps * macro_steps
    sim = softmac_mpm.MPMSimulator(_config(n, cells, total + 1), env_dt=DT * substeps)
    if sim.n_grid != cells:
        raise InputError(f"SoftMAC's grid has {sim.n_grid} cells a side for quality {cells / 64}, not {cells}")
    sim.initialize()

    def forward(first: int) -> None:
        for s in range(first, first + substeps):
            sim.substep(s)

    def backward(first: int) -> None:
        for s in reversed(range(first, first + substeps)):
            sim.substep_grad(s)

    sim.reset(pts)
    t = time.perf_counter()
    forward(0)
    _seed(sim, substeps)
    backward(0)  # compiles every kernel and its adjoint
    ti.sync()
    compile_s = time.perf_counter() - t
    sim.reset(pts)
    fwd_s = [_timed(lambda m=m: forward(m * substeps)) for m in range(macro_steps)]
    fwd_peak = _peak_mib()
    _seed(sim, total)
    bwd_s = [_timed(lambda m=m: backward(m * substeps)) for m in reversed(range(macro_steps))]
    fwd, bwd = statistics.median(fwd_s), statistics.median(bwd_s)  # its forward is the recorded one
    row = result_row(
        dim, precision, cells, n, substeps, macro_steps, arch, (fwd, fwd, bwd), (base, fwd_peak, _peak_mib())
    )
    return row | {
        "threads": int(ti.lang.impl.current_cfg().cpu_max_num_threads) if arch == "cpu" else 0,
        "scatter": "atomic",
        "field_MiB": float("nan"),
        "compile_s": compile_s,
        "package": str(Path(softmac_mpm.__file__).resolve().parents[1]),
    }


def _seed(sim, frame: int) -> None:
    """Every adjoint zero but dL/dx = 1 at ``frame`` (the loss sum x of that frame's particles)."""
    import numpy as np
    import taichi as ti

    ti.ad.clear_all_gradients()
    seed = np.zeros(sim.x.grad.shape + (3,))
    seed[frame] = 1.0
    sim.x.grad.from_numpy(seed)


if __name__ == "__main__":
    here = str(Path(__file__).resolve().parent)  # as ``mpm_measure``: none of this folder's modules shadows one
    sys.path[:] = [p for p in sys.path if str(Path(p or ".").resolve()) != here]
    print(json.dumps(measure(**json.loads(sys.argv[1]))))
