"""cosim: differentiable co-simulation of MPM soft bodies with rigid bodies and cloth.

The main entry points, imported lazily (``import cosim`` loads neither Taichi nor DART):

- ``load_scene(path, overrides=None) -> Scene``: a YAML scene, validated (errors name the key).
- ``build_system(scene, requires_grad=False, steps=None) -> CoupledSystem``: the engines and
  couplers the scene needs; ``system.step()`` advances one macro step, ``system.rollout()``
  all of them, ``system.vjp(record, grad)`` differentiates a recorded step.
- ``Objective(system, loss=None)``: the loss of a rollout as a function of every
  differentiable parameter the engines declare; ``evaluate(params, grad=True)``.
- ``check_gradients(objective.evaluate, params, names, scales)``: adjoint against central
  differences, each direction judged against the difference's measured noise floor
  (``DirectionCheck.passed(tolerance)``).
- ``run_scene(scene, out_dir)``: what ``cosim run`` does (trajectory, metrics, preview).

Example::

    import cosim

    scene = cosim.load_scene("scenes/pull_door.yaml", {"precision": "float64", "steps": 5})
    objective = cosim.Objective(cosim.build_system(scene, requires_grad=True))
    params = objective.initial_params()
    loss, grads = objective.evaluate(params, grad=True)
"""

from importlib import import_module

_ENTRY_POINTS = {
    "load_scene": "cosim.scene",
    "parse_scene": "cosim.scene",
    "build_system": "cosim.scene.build",
    "CoupledSystem": "cosim.system",
    "Objective": "cosim.adjoint.objective",
    "check_gradients": "cosim.adjoint.gradcheck",
    "run_scene": "cosim.run",
}

__all__ = ["CoupledSystem", "Objective", "build_system", "check_gradients", "load_scene", "parse_scene", "run_scene"]


def __getattr__(name: str):
    if name in _ENTRY_POINTS:
        return getattr(import_module(_ENTRY_POINTS[name]), name)
    raise AttributeError(f"module 'cosim' has no attribute '{name}'")
