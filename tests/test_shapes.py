"""The shape vocabulary (cosim.engines.shapes) is the one the SDFs, DART specs and scene schema use."""

import typing

import numpy as np
import pytest

from cosim.couplers.sdf import primitive_distance, primitive_extent
from cosim.engines import shapes
from cosim.engines.rigid_build import ShapeSpec, check_shape
from cosim.errors import InputError

SIZES = {"size": [0.2, 0.1], "radius": 0.1, "height": 0.3, "thickness": 0.02}


@pytest.mark.parametrize("kind", list(shapes.PRIMITIVE_SIZES))
def test_every_primitive_kind_has_a_closed_form_sdf_from_its_size_keys(kind):
    """The table's keys are exactly what the SDF needs: the distance at the centre of a solid
    primitive is minus its smallest half extent (containers: positive, the centre is in the cavity)."""
    size = {k: SIZES[k] for k in shapes.PRIMITIVE_SIZES[kind]}
    if kind == "box":
        size = {"half": 0.5 * np.asarray(size["size"])}
    half = primitive_extent(kind, 2, **size)
    d = primitive_distance(kind, np.zeros((1, 2)), **size)[0]
    if kind in shapes.CONTAINER_KINDS:
        assert d > 0
    else:
        assert d == pytest.approx(-min(half), abs=1e-15)


def test_dart_specs_need_the_tables_keys():
    for kind in shapes.DART_SHAPE_KINDS:
        first = shapes.required_keys(kind, mesh_key="mesh")[0]  # the first missing key is named
        with pytest.raises(InputError, match=f"a {kind} shape needs '{first}'"):
            check_shape(ShapeSpec(kind), "link")
    with pytest.raises(InputError, match="unknown shape kind 'glass'; use one of box, sphere, cylinder, capsule, mesh"):
        check_shape(ShapeSpec("glass"), "link")


def test_the_scene_schema_offers_the_tables_rigid_kinds():
    from cosim.scene import RigidShape

    assert set(typing.get_args(RigidShape.model_fields["type"].annotation)) == set(shapes.RIGID_SHAPE_KINDS)
