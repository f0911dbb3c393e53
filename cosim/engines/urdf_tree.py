"""A URDF's kinematic tree read with xml.etree (no DART): links, joints, and what makes it no tree.

DART's loader accepts some broken files (a joint to an unknown link, a cycle) and fails on others
without saying why; ``read_urdf_tree`` finds those faults first, each named with the file, so
``cosim validate`` refuses what ``cosim run`` would and the user learns which link or joint to fix.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from cosim.errors import InputError


@dataclass(frozen=True)
class UrdfTree:
    """Link names, and per joint its name, type, parent link and child link; ``root`` the one link
    no joint moves."""

    links: tuple[str, ...]
    joints: tuple[tuple[str, str, str, str], ...]  # (name, type, parent, child)
    root: str

    @property
    def joint_names(self) -> list[str]:
        return [j[0] for j in self.joints]


def read_urdf_tree(path: str | Path, error: type[Exception] = InputError) -> UrdfTree:
    """Parse ``path`` and check it is one tree: XML well formed, unique link and joint names, every
    joint between two known links, each link with at most one parent, one root, no cycle."""
    path = Path(path)
    where = f"URDF {path}"
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise error(f"{where} is not readable XML: {exc}; fix the file there") from None
    if root.tag != "robot":
        raise error(f"{where}: the top element is <{root.tag}>, a URDF's is <robot>")
    links = [lk.get("name") for lk in root.findall("link")]
    if not links or None in links:
        raise error(f"{where}: every <link> needs a name, and a robot at least one link")
    _unique(links, "link", where, error)
    joints = []
    for j in root.findall("joint"):
        name, parent, child = j.get("name"), j.find("parent"), j.find("child")
        if name is None or parent is None or child is None:
            raise error(f"{where}: joint '{name}' needs a name, a <parent link=...> and a <child link=...>")
        pair = (parent.get("link"), child.get("link"))
        for role, link in zip(("parent", "child"), pair):
            if link not in links:
                raise error(f"{where}: joint '{name}' names {role} link '{link}', which is not a <link> of the file")
        joints.append((name, j.get("type", ""), *pair))
    _unique([j[0] for j in joints], "joint", where, error)
    parents: dict[str, str] = {}
    for name, _, parent, child in joints:
        if child in parents:
            raise error(f"{where}: link '{child}' is the child of two joints ('{parents[child]}' and '{name}')")
        parents[child] = name
    roots = [lk for lk in links if lk not in parents]
    if len(roots) != 1:
        raise error(
            f"{where}: a URDF is one tree with one root link, this one has {len(roots)} "
            f"({roots or 'every link has a parent: the joints form a cycle'}); connect or remove links"
        )
    _check_acyclic(links, joints, where, error)
    return UrdfTree(tuple(links), tuple(joints), roots[0])


def _unique(names: list[str], what: str, where: str, error) -> None:
    seen = {n for n in names if names.count(n) > 1}
    if seen:
        raise error(f"{where}: {what} names must be unique; repeated: {sorted(seen)}")


def _check_acyclic(links: list[str], joints: list, where: str, error) -> None:
    """Walk up from every link; with one parent per link a cycle is a walk that comes back."""
    parent_of = {child: (name, parent) for name, _, parent, child in joints}
    for start in links:
        seen, link = [], start
        while link in parent_of:
            if link in seen:
                cycle = " -> ".join(parent_of[lk][0] for lk in seen[seen.index(link) :])
                raise error(f"{where}: the joints form a cycle ({cycle}); a URDF must be a tree")
            seen.append(link)
            link = parent_of[link][1]
