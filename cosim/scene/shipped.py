"""The scenes shipped with cosim: the repository's ``scenes/`` folder, installed as ``cosim.scenes``.

Here rather than in the CLI so that benchmarks and tests find them without importing the CLI.
"""

from __future__ import annotations

from pathlib import Path


def scenes_dir() -> Path:
    """The folder of the shipped scene files (``*.yaml``) and their assets."""
    from importlib import resources

    return Path(str(resources.files("cosim.scenes")))
