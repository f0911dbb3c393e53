"""The package list, which pyproject.toml cannot give: every ``cosim*`` package on disk (a new one
cannot be left out) plus ``cosim.scenes``, the top-level ``scenes/`` folder (see its package-dir)."""

from setuptools import find_packages, setup

setup(packages=[*find_packages(include=["cosim*"]), "cosim.scenes"])
