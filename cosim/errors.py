"""Errors a user can act on. The CLI turns them into one message and an exit code."""

from __future__ import annotations


class CosimError(Exception):
    """Base class: a message in the user's terms (scene key, body name, step)."""

    exit_code = 1


class SceneError(CosimError):
    """The scene file is wrong: bad key, type, range, or a missing/unusable file."""

    exit_code = 2


class InputError(CosimError):
    """A file given on the command line is missing or not what it should be."""

    exit_code = 2


class SimulationError(CosimError):
    """The simulation became invalid: CFL violated, NaN/inf, a particle left the domain."""

    exit_code = 3


class GradientCheckError(CosimError):
    """Adjoint and finite-difference gradients disagree beyond the tolerance."""

    exit_code = 4


class CouplingWarning(UserWarning):
    """The run goes on, but a coupling works outside the range where it is measured sound (a light body coupled
    with more MPM substeps per exchange than it rests stably at)."""
