"""The paper's optimisation tasks, each from its plain initial guess: `cosim optimize` lowers the loss at
every one of 3 iterations on a shortened rollout (the full runs are in the README's task table).

Only pull_door (2D) and pour_water (3D) run here: every 3D task compiles its own adjoint kernels, about
2 minutes per task on a CI core (measured: squeeze_plasticine's first adjoint step 120-130 s with Taichi's
offline cache empty, 95% of it in the reverse-mode P2G, G2P and forecast-contact kernels), and the
suite must stay under 10 minutes. The other four join when those kernels compile faster."""

from __future__ import annotations

import pytest
from conftest import check_task_improves

# task: (macro steps of the shortened rollout, the largest loss ratio after 3 iterations accepted)
TASKS = {
    "pull_door": (60, 0.95),  # measured: 0.190 -> 0.176 (-7.6% after 2 steps of 3 evaluations)
    "pour_water": (20, 0.97),  # measured: 0.1448 -> 0.1374 (-5.1%)
}


@pytest.mark.parametrize("task", sorted(TASKS))
def test_three_iterations_lower_the_loss(task, tmp_path):
    check_task_improves(task, *TASKS[task], tmp_path)
