"""The tape: per-macro-step records, replayed in reverse through the coupled system's vjp.

Forward, the rollout (``CoupledSystem.rollout``) pushes one ``StepRecord`` per macro
step: one record per engine and coupler, keyed by name (the MPM's holds the state at
the start of the step, a checkpoint, its inputs and its boundary states; the checkpoint stays on the
engine's device while it fits, ``cosim.engines.mpm_checkpoints``, and so do the state adjoints).
Backward, the tape walks the records from last to first and calls
``step_vjp(record, dL/dstate_after)`` (``CoupledSystem.vjp``: the MPM vjp recomputes
that step's substeps from its checkpoint), which returns dL/dstate_before per engine
plus the gradients of the step's inputs and parameters. Memory is one MPM state
per macro step plus one macro step of substeps in the engine:
O(S N + K N), never O(S K N).

With ``checkpoint_every`` k > 1 the tape keeps the MPM state of every k-th step only
(and of the last, which the engine still holds); the backward pass recomputes the
others one segment of k steps at a time (``CoupledSystem.restore_checkpoints``):
O(S N / k + k N + K N) memory for about one more MPM forward pass.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Gradients:
    """dL/d(inputs) of a whole rollout."""

    state0: dict[str, dict[str, np.ndarray]]  # dL/d(initial state) per engine name
    impulse: list[np.ndarray | None]  # per macro step, (N, d)
    action: dict[str, list[np.ndarray | None]] = field(default_factory=dict)  # per engine, per macro step
    material: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # per engine: {key: dL/dkey}


class Tape:
    """Records macro steps forward; ``backward`` replays them in reverse. Keeps the MPM checkpoint
    of every ``checkpoint_every``-th step (``backward`` then needs ``restore``)."""

    def __init__(self, checkpoint_every: int = 1) -> None:
        if checkpoint_every < 1:
            raise ValueError(f"checkpoint_every must be at least 1 (got {checkpoint_every})")
        self.checkpoint_every = checkpoint_every
        self.records: list = []

    def push(self, record) -> None:
        """Append a step; the previous one's checkpoint is released unless it is a k-th one (the last
        step keeps its own: the engine still holds that step, so the backward starts without a replay)."""
        if self.records:
            self._release(len(self.records) - 1)
        record.keep_checkpoint(record.checkpoint)  # in the engine's precision
        self.records.append(record)

    def _release(self, n: int) -> None:
        if n % self.checkpoint_every:
            self.records[n].keep_checkpoint(None)

    def clear(self) -> None:
        self.records.clear()

    @property
    def nbytes(self) -> int:
        """Memory held by the records [bytes]: checkpoints (host or device), impulses, boundary states."""
        return sum(r.nbytes for r in self.records)

    def backward(
        self,
        step_vjp: Callable,
        grad_final: dict[str, dict[str, np.ndarray]],
        running: list[dict | None] | None = None,
        restore: Callable[[list], None] | None = None,
    ) -> Gradients:
        """Chain rule over the recorded steps: dL/ds^n = dL/ds^{n+1} ds^{n+1}/ds^n + dl_n/ds^n.

        ``step_vjp(record, dL/dstate_after)`` differentiates one step (``CoupledSystem.vjp``) and
        returns "state" (per engine), "impulse", "action" (per engine) and "material".
        ``running[n]`` (n = 0..S) is the gradient of the loss terms read at state n (running
        terms; None where there are none): it joins the adjoint as the pass reaches state n.
        ``restore(records)`` refills the checkpoints of ``records[1:]`` from ``records[0]``'s
        (``CoupledSystem.restore_checkpoints``); needed with ``checkpoint_every`` > 1.
        """
        running = running or [None] * (len(self.records) + 1)
        if len(running) != len(self.records) + 1:
            raise ValueError(f"running gradients: {len(running)} states for {len(self.records)} steps")
        grad_state = _plus(grad_final, running[-1])
        n_steps = len(self.records)
        impulses: list[np.ndarray | None] = [None] * n_steps
        actions: dict[str, list] = {}
        material: dict[str, dict[str, np.ndarray]] = {}
        for n in reversed(range(n_steps)):
            if self.records[n].checkpoint is None:
                self._restore_segment(n, restore)
            out = step_vjp(self.records[n], grad_state)
            self._release(n)
            _check_finite(out, n)
            grad_state = _plus(out["state"], running[n])
            impulses[n] = out.get("impulse")
            for name, g in out["action"].items():
                actions.setdefault(name, [None] * n_steps)[n] = g
            for engine, grads in out["material"].items():
                totals = material.setdefault(engine, {})
                for key, g in grads.items():
                    totals[key] = totals.get(key, 0.0) + g
        return Gradients(state0=grad_state, impulse=impulses, action=actions, material=material)

    def _restore_segment(self, n: int, restore: Callable[[list], None] | None) -> None:
        """Recompute the checkpoints of the steps after the last one kept before step n, up to n."""
        if restore is None:
            raise ValueError("the tape keeps every k-th checkpoint only: backward needs restore=")
        first = n - n % self.checkpoint_every
        restore(self.records[first : n + 1])


def _plus(grad: dict[str, dict[str, np.ndarray]], extra: dict | None) -> dict[str, dict[str, np.ndarray]]:
    """grad + extra per engine and key (extra may be None); new arrays, the inputs untouched. Only the
    engines in ``extra`` are read (an MPM state adjoint may be on the device: ``DeviceState``)."""
    if extra is None:
        return grad
    out = dict(grad)
    for name, g in extra.items():
        summed = dict(grad.get(name, {}))
        for key, value in g.items():
            summed[key] = summed.get(key, 0.0) + value
        out[name] = summed
    return out


def _check_finite(out: dict, n: int) -> None:
    """Stop where the adjoint first turns non-finite (the backward pass meets steps from the last to the
    first, so the first bad step met is where it starts), naming the macro step, engine and quantity."""
    from cosim.errors import SimulationError

    groups = {}
    for engine, grads in out["state"].items():  # "couplers": {coupler: {key: gradient}}
        if hasattr(grads, "nonfinite"):  # a state adjoint on the device checks itself there
            groups.update({f"{engine}.{key}": np.nan for key in grads.nonfinite()})
            continue
        for key, g in grads.items():
            groups.update({f"{key}.{k}": v for k, v in g.items()} if isinstance(g, dict) else {f"{engine}.{key}": g})
    groups.update({f"{engine}.action": g for engine, g in out["action"].items() if g is not None})
    for engine, grads in out["material"].items():
        groups.update({f"{engine}.{key}": g for key, g in grads.items()})
    if out.get("impulse") is not None:
        groups["mpm.impulse"] = out["impulse"]
    for name, g in groups.items():
        if not np.all(np.isfinite(g)):
            raise SimulationError(
                f"gradient: dL/d({name}) is not finite at macro step {n} (the backward pass reached it from the "
                "end); the forward step there is likely unstable: check its CFL and contact, or lower time.frame_dt"
            )
