"""The one mesh-file loader: scaling per axis, and an error naming the key, the file and the fix
for a missing, unreadable, empty or open mesh."""

import numpy as np
import pytest
import trimesh

from cosim.engines.meshes import load_mesh, require_watertight
from cosim.errors import InputError, SceneError


def test_scale_is_per_axis_or_uniform(tmp_path):
    path = tmp_path / "cube.obj"
    trimesh.creation.box(extents=(1.0, 1.0, 1.0)).export(path)
    assert np.allclose(load_mesh(path, (0.1, 0.2, 0.3)).extents, [0.1, 0.2, 0.3], rtol=1e-12)
    assert np.allclose(load_mesh(str(path), 0.5).extents, [0.5, 0.5, 0.5], rtol=1e-12)


def test_bad_files_name_the_key_the_file_and_the_fix(tmp_path):
    with pytest.raises(SceneError, match=r"^bodies\[0\].file: mesh file not found: .*nope.obj; fix the path"):
        load_mesh(tmp_path / "nope.obj", key="bodies[0].file", error=SceneError)
    (tmp_path / "bad.abc").write_text("garbage")
    with pytest.raises(InputError, match=r"^cannot read mesh .*bad.abc: .*; export it as OBJ/STL"):
        load_mesh(tmp_path / "bad.abc")
    (tmp_path / "empty.obj").write_text("")
    with pytest.raises(InputError, match=r"empty.obj has no triangles"):
        load_mesh(tmp_path / "empty.obj")


def test_an_open_mesh_is_refused_with_the_callers_reason():
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    require_watertight(box, "box", "it has no volume", "close it")  # closed: no error
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    with pytest.raises(SceneError, match="^k: box is not watertight, so it has no volume; close it$"):
        require_watertight(open_box, "k: box", "it has no volume", "close it", SceneError)
