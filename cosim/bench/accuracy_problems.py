"""The reference problems of ``cosim bench accuracy``, by name (see ``accuracy_problem`` for what one is).

| name | what | compared with |
|---|---|---|
| dam_break | liquid: a water column's front along a tank (2D) | reference run |
| elastic_bar | elastic: a free strip's fundamental longitudinal period (2D) | closed form (plane-strain bar) |
| plastic_drop | plastic: a plasticine cube's height after hitting the floor (3D) | reference run |
| buoyancy | rigid + liquid: a floating box's submerged fraction (2D) | Archimedes |
| contact | a block resting on a rigid support, per contact model (2D) | closed form (self-weight) |
| gradient | the adjoint d(bar displacement)/d ln E (2D) | closed form |
"""

from __future__ import annotations

from cosim.bench.accuracy_coupled import FloatingBox, RestingBlock
from cosim.bench.accuracy_gradient import BarGradient
from cosim.bench.accuracy_problem import Problem
from cosim.bench.accuracy_soft import BarVibration, DamBreak, PlasticDrop

PROBLEMS: dict[str, Problem] = {
    p.name: p for p in (DamBreak(), BarVibration(), PlasticDrop(), FloatingBox(), RestingBlock(), BarGradient())
}
