"""The paper's optimisation tasks, each from its plain initial guess: `cosim optimize` lowers the loss at
every one of 3 iterations on a shortened rollout (the full runs' latest results are in docs/tasks.md).

The six tasks are split over three files (this one, test_tasks_manipulation.py, test_tasks_cloth.py) so
that the suite's two workers share them: each 3D task compiles its kernels and their adjoints for about
a minute with Taichi's cache empty."""

from __future__ import annotations

import pytest
from conftest import check_task_improves

# task: (macro steps of the shortened rollout, the largest loss ratio after 3 iterations accepted)
TASKS = {
    # the whole rollout: on 30-100 steps the gripper only starts to touch the handle and Adam's first
    # steps (lr x scale on each of the 23,400 impulses) raise the loss; measured 0.164 -> 0.066
    "pull_door": (150, 0.6),
    "pour_water": (10, 0.995),  # measured: 0.1506 -> 0.1489 (-1.1%)
}
LONG = {"pull_door"}  # with the four 3D tasks: -m long_task


@pytest.mark.slow
@pytest.mark.parametrize(
    "task", [pytest.param(t, marks=[pytest.mark.long_task] if t in LONG else []) for t in sorted(TASKS)]
)
def test_three_iterations_lower_the_loss(task, tmp_path):
    check_task_improves(task, *TASKS[task], tmp_path)
