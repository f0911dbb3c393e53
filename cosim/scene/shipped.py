"""The scenes shipped with cosim: the repository's ``scenes/`` folder, installed as ``cosim.scenes``.

Here rather than in the CLI so that benchmarks and tests find them without importing the CLI.
"""

from __future__ import annotations

from pathlib import Path

from cosim.errors import SceneError


def scenes_dir() -> Path:
    """The folder of the shipped scene files (``*.yaml``) and their assets."""
    from importlib import resources

    try:
        return Path(str(resources.files("cosim.scenes")))
    except ModuleNotFoundError:  # a checkout on PYTHONPATH, not installed: the repository's scenes/
        return Path(__file__).resolve().parents[2] / "scenes"


PYBULLET_DATA = "pybullet_data:"  # prefix of paths inside the optional pybullet wheel's data folder


def resolve_asset(text: str, source_dir: Path, key: str) -> Path:
    """A scene path: relative to the scene, or ``pybullet_data:sub/path`` inside the data folder of
    the optional ``pybullet`` wheel (``pip install -e ".[panda]"``: the real Franka Panda meshes)."""
    if not text.startswith(PYBULLET_DATA):
        return (source_dir / text).resolve()
    try:
        import pybullet_data
    except ImportError:
        raise SceneError(
            f"{key}: '{text}' needs the optional pybullet wheel: pip install -e \".[panda]\" "
            "(or use our scenes/assets/panda_like arm, which needs nothing)"
        ) from None
    return Path(pybullet_data.getDataPath()) / text[len(PYBULLET_DATA) :]
