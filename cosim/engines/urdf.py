"""URDF skeletons: DART's URDF loader for the dynamics, our own parse of the ``<collision>`` geometry.

DART builds the bodies, joints and inertias; ``urdf_geometry`` reads every link's ``<collision>`` elements
(xml.etree) into ``ShapeSpec``s in the link frame, with mesh references (``package://``, ``file://`` or
relative to the URDF) resolved to absolute paths, so the MPM coupler sees the same shapes DART collides.
URDF lengths are in metres and ``rpy`` in radians (converted to the specs' Euler degrees).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import dartpy as dart
import numpy as np

from cosim.engines.rigid_specs import ShapeSpec, SkeletonSpec, dof_vector, isometry
from cosim.errors import InputError


def build_urdf_skeleton(spec: SkeletonSpec):
    """A DART skeleton from a URDF: floating or welded root, all finite joint limits enforced."""
    path = _urdf_path(spec)
    urdf_geometry(spec)  # checks every collision mesh resolves, with errors naming the file
    loader = dart.utils.DartLoader()
    for name, folder in spec.package_dirs.items():
        loader.addPackageDirectory(name, str(Path(folder).resolve()))
    options = loader.getOptions()
    root = dart.utils.DartLoaderRootJointType
    options.mDefaultRootJointType = root.FIXED if spec.fixed_base else root.FLOATING
    loader.setOptions(options)
    skel = loader.parseSkeleton(dart.common.Uri(f"file://{path}"))
    if skel is None:
        raise InputError(f"DART could not parse URDF {path}; check it with check_urdf and the package_dirs")
    skel.setName(spec.name)
    if spec.base_transform is not None:
        skel.getRootJoint().setTransformFromParentBodyNode(isometry(spec.base_transform))
    for joint in skel.getJoints():
        limits = np.concatenate([joint.getPositionLowerLimits(), joint.getPositionUpperLimits()])
        if np.isfinite(limits).any():
            joint.setLimitEnforcement(True)
    joints = {j.getName(): j for j in skel.getJoints()}
    for name, value in spec.initial_positions.items():
        if name not in joints:
            raise InputError(
                f"skeleton '{spec.name}': initial_positions names unknown joint '{name}'; joints: {sorted(joints)}"
            )
        joint = joints[name]
        joint.setPositions(dof_vector(value, joint.getNumDofs(), f"skeleton '{spec.name}', joint '{name}'"))
    return skel


def _urdf_path(spec: SkeletonSpec) -> Path:
    path = Path(spec.urdf).resolve()
    if not path.is_file():
        raise InputError(f"skeleton '{spec.name}': URDF file not found: {spec.urdf}; fix the 'urdf' path")
    return path


def resolve_uri(filename: str, urdf_dir: Path, package_dirs: dict[str, str], where: str) -> str:
    """Absolute path of a URDF mesh reference (package://, file:// or relative to the URDF); must exist."""
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://") :].partition("/")
        if package not in package_dirs:
            raise InputError(f"{where}: mesh '{filename}' uses package '{package}'; add it to package_dirs")
        path = Path(package_dirs[package]) / rest
    elif filename.startswith("file://"):
        path = Path(filename[len("file://") :])
    else:
        path = urdf_dir / filename
    path = path.resolve()
    if not path.is_file():
        raise InputError(f"{where}: mesh file not found: {path} (from '{filename}')")
    return str(path)


def urdf_geometry(spec: SkeletonSpec) -> dict[str, list[ShapeSpec]]:
    """Collision shapes of every URDF link (link frame), parsed with xml.etree; mesh paths made absolute."""
    path = _urdf_path(spec)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(f"URDF {path} is not valid XML: {exc}") from exc
    out: dict[str, list[ShapeSpec]] = {}
    for link in root.findall("link"):
        name = link.get("name")
        out[name] = [
            _urdf_shape(c, path.parent, spec.package_dirs, f"URDF {path.name}, link '{name}'")
            for c in link.findall("collision")
        ]
    return out


def _floats(text: str | None, default) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split()) if text else tuple(default)


def _urdf_shape(collision, urdf_dir: Path, package_dirs: dict[str, str], where: str) -> ShapeSpec:
    origin = collision.find("origin")
    xyz = _floats(origin.get("xyz") if origin is not None else None, (0, 0, 0))
    rpy = _floats(origin.get("rpy") if origin is not None else None, (0, 0, 0))
    pose = {"position": xyz, "rotation": tuple(math.degrees(a) for a in rpy)}
    geom = collision.find("geometry")
    g = next(iter(geom), None) if geom is not None else None
    if g is None:
        raise InputError(f"{where}: <collision> without a <geometry> child")
    if g.tag == "box":
        return ShapeSpec("box", size=_floats(g.get("size"), ()), **pose)
    if g.tag == "sphere":
        return ShapeSpec("sphere", radius=float(g.get("radius")), **pose)
    if g.tag in ("cylinder", "capsule"):
        return ShapeSpec(g.tag, radius=float(g.get("radius")), height=float(g.get("length")), **pose)
    if g.tag == "mesh":
        mesh = resolve_uri(g.get("filename", ""), urdf_dir, package_dirs, where)
        scale = _floats(g.get("scale"), (1, 1, 1))
        return ShapeSpec("mesh", mesh=mesh, scale=tuple(np.broadcast_to(scale, 3)), **pose)
    raise InputError(f"{where}: unsupported collision geometry <{g.tag}>; use box, sphere, cylinder or mesh")
