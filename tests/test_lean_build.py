"""A scene pays only for what it uses: a pure-MPM run builds no contact hook, imports no DART or
cloth engine, allocates no gradient buffers, and compiles no material it does not contain."""

import json
import subprocess
import sys

from conftest import ROOT

PROBE = """
import json, sys
from cosim.scene import load_scene
from cosim.scene.build import build_system

scene = load_scene("scenes/elastic_bounce_2d.yaml", {"precision": "float64"})
sim = build_system(scene, requires_grad=False, steps=2)
for _ in range(2):
    sim.step()
mpm = sim.mpm


def placed(field):
    try:  # an adjoint Taichi did not allocate has no shape
        return field.shape is not None
    except AttributeError:
        return False


def materials(name, at):  # the material template argument of each compiled instance of kernel ``name``
    return sorted({type(key[at]()).__name__ for key in getattr(type(mpm), name)._primal.mapper.mapping})


compiled = {"_p2g": materials("_p2g", 2), "_g2p_advect": materials("_g2p_advect", 1)}  # (after self, scatter)
compiled["_substep_fused"] = len(type(mpm)._substep_fused._primal.mapper.mapping)  # its materials: the engine's
print(json.dumps({
    "modules": sorted(m for m in sys.modules if m.split(".")[0] == "dartpy" or m.startswith(("cosim.engines.rigid", "cosim.engines.cloth"))),
    "hooks": len(mpm.grid_hooks) + len(mpm.particle_hooks),
    "grad_buffers": [placed(getattr(mpm, k).grad) for k in ("x", "v", "C", "F")],
    "materials_compiled": compiled,
    "engine_materials": sorted({type(m).__name__ for m in mpm.materials}),
}))
"""


def test_a_pure_mpm_run_builds_imports_and_compiles_only_the_mpm():
    result = subprocess.run(
        [sys.executable, "-c", PROBE], check=False, capture_output=True, text=True, cwd=ROOT, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    seen = json.loads(result.stdout.strip().splitlines()[-1])
    assert seen["modules"] == []  # neither dartpy nor our rigid or cloth engines
    assert seen["hooks"] == 0  # no contact model on the grid or the particles
    assert seen["grad_buffers"] == [False] * 4
    # the forward substep is one kernel over the engine's materials, compiled once; the separate ones never
    assert seen["materials_compiled"] == {"_p2g": [], "_g2p_advect": [], "_substep_fused": 1}
    assert seen["engine_materials"] == ["Elastic"]  # no return mapping
