"""Taichi's front end with memoised source positions (``cosim.engines.taichi_frontend``) formats every node
as Taichi does: the IR, its cache key and Taichi's error messages stay the same."""

from conftest import SCENES

from cosim.engines import taichi_frontend
from cosim.scene import load_scene
from cosim.scene.build import build_system


def test_every_memoised_position_of_a_coupled_scenes_kernels_is_taichis_own(monkeypatch):
    """A fresh shake_container_2d (MPM, grid contact, a kinematic container, the guards) built and stepped:
    each node's position string from the memo equals Taichi's formatting of that node, over thousands of
    nodes of which most are built more than once (inlined functions, unrolled static loops)."""
    seen, differing = [], []

    def checked(ctx, node):
        memoised = taichi_frontend._get_pos_info(ctx, node)
        if memoised != taichi_frontend.taichi_positions(ctx, node):
            differing.append((ctx.file, node.lineno, type(node).__name__))
        seen.append(memoised)
        return memoised

    monkeypatch.setattr(taichi_frontend._Context, "get_pos_info", checked)
    scene = load_scene(SCENES / "shake_container_2d.yaml", {"precision": "float64", "steps": 2})
    sim = build_system(scene)
    sim.step()
    assert differing == []
    assert len(seen) > 2000 and len(set(seen)) < 0.6 * len(seen), (len(seen), len(set(seen)))
