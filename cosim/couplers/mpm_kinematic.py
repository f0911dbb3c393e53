"""Kinematic bodies as MPM boundaries: prescribed motions in, reactions recorded but not fed back.

A kinematic body's motion is prescribed, so the reactions the MPM hands back move
nothing (they stay readable in the step's outputs, for metrics and tests) and no
gradient flows into the motion: ``forces_vjp`` gives zero reaction adjoints and
``boundary_vjp`` a zero state gradient. Conforms to ``cosim.engines.contract.Coupler``.
"""

from __future__ import annotations

import numpy as np

from cosim.engines.kinematic import KinematicEngine, kinematic_states


class MPMKinematicCoupler:
    def __init__(self, kinematic: KinematicEngine, name: str = "kinematic"):
        self.kinematic = kinematic
        self.name = self.source = name
        self.engine = kinematic.name
        self.medium = "mpm"

    def boundary(self, dt: float, substeps: int) -> tuple[dict, None]:
        """Poses and twists of the motions at the start of each substep of the current frame."""
        return kinematic_states(self.kinematic.motions, self.kinematic.time, dt, substeps), None

    def budgeted(self) -> bool:
        """Prescribed motions: the energy budget does not hold them; their contact work is external."""
        return False

    def forces(self, record: None, reactions: dict) -> dict:
        return {}

    def forces_vjp(self, record: None, grad_load: dict, grad_state: None = None) -> tuple[None, None, None]:
        return None, None, None

    def boundary_vjp(self, record: None, grad_boundary: dict, carry: None) -> dict[str, np.ndarray]:
        return {"steps": np.zeros(1)}
