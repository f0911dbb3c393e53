"""The differentiable parameters a scene has, by the names ``gradient.params`` and ``optimize.params`` use.

Every scene has the MPM's ``x0``, ``v0``, ``E`` and ``nu``; ``impulse`` needs ``controls:``,
``action`` a skeleton (``articulated:``) or cloth with controls, and the cloth materials
(``k_stretch``, ``k_bend``, ``c_mass``, ``density``) a ``cloth:`` section. A name selects that
parameter of every engine that declares it (``Objective.select``: ``x0`` and ``v0`` are a
cloth's too). The loader refuses a list the scene cannot serve (``params_problems``); the
commands that build the objective check its selection again with the same message
(``select_params``), so no list reaches them empty.
"""

from __future__ import annotations

from cosim.errors import SceneError

MPM_PARAMS = ("x0", "v0", "E", "nu")
CLOTH_MATERIAL_PARAMS = ("k_stretch", "k_bend", "c_mass", "density")  # cosim.engines.cloth.MATERIAL_KEYS
SECTIONS = ("gradient", "optimize")

_NEEDS = {
    "impulse": "impulse needs an entry under controls:",
    "action": "action needs a skeleton with controls under articulated:, or a cloth with controls",
    **{k: f"{k} is a cloth's material: it needs a cloth: section" for k in CLOTH_MATERIAL_PARAMS},
}


def scene_parameters(scene) -> list[str]:
    """The parameter names ``scene`` has (module docstring), in a fixed order."""
    names = list(MPM_PARAMS)
    if scene.controls:
        names.append("impulse")
    skeletons = scene.articulated.skeletons if scene.articulated is not None else []
    if any(s.controls for s in skeletons) or any(c.controls for c in scene.cloth):
        names.append("action")
    if scene.cloth:
        names += CLOTH_MATERIAL_PARAMS
    return names


def params_problem(key: str, asked: list[str], available: list[str]) -> list[str]:
    """What is wrong with the names ``asked`` at ``key`` (e.g. ``gradient.params``) where ``available``
    are the scene's: an empty list, or each name the scene does not have (with why, and the names it has)."""
    if not asked:
        return [f"{key}: an empty list; name at least one of this scene's parameters {available}"]
    unknown = [name for name in dict.fromkeys(asked) if name not in available]
    return [
        f"{key}: '{name}' is not a parameter of this scene ({_NEEDS.get(name, 'unknown name')}); it has {available}"
        for name in unknown
    ]


def given(scene, section: str) -> bool:
    """Whether the scene gives ``<section>.params`` itself (a file, ``--set``), not the default."""
    return section in scene.model_fields_set and "params" in getattr(scene, section).model_fields_set


def params_problems(scene) -> list[str]:
    """The loader's check of ``gradient.params`` and ``optimize.params`` where the scene gives them
    (the defaults ask for what a scene usually has, and skip what it lacks)."""
    available = scene_parameters(scene)
    problems = []
    for section in SECTIONS:
        if given(scene, section):
            problems += params_problem(f"{section}.params", getattr(scene, section).params, available)
    return problems


def select_params(objective, scene, section: str) -> list[str]:
    """The objective's parameters ``scene.<section>.params`` selects (``Objective.select``), checked
    against the parameters the objective declares: a list the scene gives, as the loader checks it
    (``params_problem``); the default, that it selects something."""
    key, asked = f"{section}.params", getattr(scene, section).params
    available = list(dict.fromkeys(name.split(".", 1)[-1] for name in objective.parameters))
    names = objective.select(asked)
    problems = params_problem(key, asked, available) if given(scene, section) else []
    if not names and not problems:
        problems = [f"{key}: none of the default {asked} is a parameter of this scene; give {key} from {available}"]
    if problems:
        raise SceneError("\n  ".join(problems))
    return names
