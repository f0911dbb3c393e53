"""The scene package: the YAML scene format, its loading and its validation.

``from cosim.scene import Scene, load_scene, parse_scene`` is the public entry;
the modules behind it:

- ``schema``: the pydantic models, one per section of the YAML file;
- ``messages``: pydantic's errors as ``key.path[i]: message`` lines;
- ``checks``: what spans several keys (vector lengths against ``dim``, names, files);
- ``accuracy``: the ``accuracy: coarse | default | fine`` hint (grid refinement, CFL number, precision),
  applied to the parsed YAML before the schema;
- ``loader``: ``load_scene`` / ``parse_scene``, which run the schema, then the checks;
- ``params``: the parameter names ``gradient.params`` / ``optimize.params`` may use in a scene;
- ``particles``: the soft bodies sampled into particles with NumPy only (``cosim validate``);
- ``shipped``: where the scenes shipped with cosim and their assets are (``scenes_dir``, ``resolve_asset``);
- ``preflight`` and ``start``: every check ``cosim run`` makes before its first step, and the host-side
  parts they build (``check_start``: ``cosim validate`` runs it, ``build_system`` builds on it);
- ``build``: the scene made runnable, ``build_system(scene) -> CoupledSystem`` (only what it uses);
- ``articulated``: DART skeletons, link SDFs and mass properties of the ``articulated:`` section.

Dependencies point one way: schema <- messages, checks <- loader; accuracy <- loader. Nothing here imports
Taichi or DART at module level (``build`` and ``articulated`` import them when called).

The reference of every key is ``docs/scene-format.md``.
"""

from cosim.scene.loader import load_scene, parse_scene
from cosim.scene.schema import (
    ActionSpec,
    ArticulatedSpec,
    BodySpec,
    BoundarySpec,
    BoxShape,
    ContactSpec,
    ControlSpec,
    CylinderShape,
    ElasticMaterial,
    GradientSpec,
    GridSpec,
    JointSceneSpec,
    LinkSceneSpec,
    LiquidMaterial,
    LossSpec,
    Material,
    MeshShape,
    MotionSegment,
    MotionSpec,
    MPMSpec,
    OptimizeSpec,
    OutputSpec,
    PlacedShape,
    PlasticMaterial,
    Positive,
    RegionSpec,
    RigidBodySpec,
    RigidShape,
    RigidSpec,
    Scene,
    Shape,
    SkeletonSceneSpec,
    SphereShape,
    Strict,
    TimeSpec,
    Vec,
)

__all__ = [
    "ActionSpec",
    "ArticulatedSpec",
    "BodySpec",
    "BoundarySpec",
    "BoxShape",
    "ContactSpec",
    "ControlSpec",
    "CylinderShape",
    "ElasticMaterial",
    "GradientSpec",
    "GridSpec",
    "JointSceneSpec",
    "LinkSceneSpec",
    "LiquidMaterial",
    "LossSpec",
    "MPMSpec",
    "Material",
    "MeshShape",
    "MotionSegment",
    "MotionSpec",
    "OptimizeSpec",
    "OutputSpec",
    "PlacedShape",
    "PlasticMaterial",
    "Positive",
    "RegionSpec",
    "RigidBodySpec",
    "RigidShape",
    "RigidSpec",
    "Scene",
    "Shape",
    "SkeletonSceneSpec",
    "SphereShape",
    "Strict",
    "TimeSpec",
    "Vec",
    "load_scene",
    "parse_scene",
]
