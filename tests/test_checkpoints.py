"""Where a gradient run keeps its MPM states (``cosim.engines.mpm_checkpoints``): on the device, on the
host, or both past a budget, the gradients are the same bit for bit; on the device no particle state
crosses to the host between the seed and the result; freed buffers are reused; a NaN in an adjoint
on the device is found there and named; the memory estimate predicts how many checkpoints the device
holds."""

from __future__ import annotations

import gc

import numpy as np
import pytest
from test_gradients import three_material_scene

from cosim.adjoint.objective import Objective
from cosim.adjoint.tape import Tape, _check_finite
from cosim.engines.mpm_checkpoints import CheckpointStore, DeviceState
from cosim.errors import SimulationError
from cosim.scene.build import build_system

STEPS = 4


def objective(where: str = "auto", checkpoint_every: int = 1) -> Objective:
    scene = three_material_scene(steps=STEPS, substeps=3)
    scene.gradient.checkpoints = where
    return Objective(build_system(scene, requires_grad=True), checkpoint_every=checkpoint_every)


def limit_device(obj: Objective, states: float) -> CheckpointStore:
    """Give ``obj``'s engine a store whose device holds ``states`` states' worth of bytes."""
    mpm = obj.system.mpm
    mpm.checkpoints = CheckpointStore(mpm, "auto", int(states * mpm.checkpoints.state_bytes))
    return mpm.checkpoints


@pytest.fixture(scope="module")
def host_run():
    """The reference: every checkpoint and adjoint as host arrays."""
    obj = objective("host")
    params = obj.initial_params()
    return params, obj.evaluate(params, grad=True)


@pytest.mark.parametrize(
    "where, device_states, every",
    [("device", None, 1), ("auto", 2.5, 1), ("device", None, 3)],
    ids=["device", "device-then-host", "device-every-3rd"],
)
def test_the_gradients_do_not_depend_on_where_the_states_are_kept(host_run, where, device_states, every):
    """Same loss and gradients bit for bit (the same kernels on the same numbers, only the copies
    differ): all on the device; the first 2 states on the device and the rest on the host (a budget of
    2.5 states); every 3rd checkpoint on the device and the rest recomputed. A copy that lost a key,
    a slot or precision would move the gradients by far more than round-off."""
    params, (value, grads) = host_run
    obj = objective(where, every)
    if device_states is not None:
        store = limit_device(obj, device_states)
    obj.rollout(params, record=True)
    kinds = {type(r.checkpoint) for r in obj.tape.records if r.checkpoint is not None}
    assert kinds == ({DeviceState, dict} if device_states else {DeviceState})
    got_value, got = obj.evaluate(params, grad=True)
    assert got_value == value
    for key in grads:
        np.testing.assert_array_equal(got[key], grads[key], err_msg=key)
    if device_states is not None:
        assert store.allocated == 2 * store.state_bytes  # the budget held: no third set of buffers


def test_a_device_tape_moves_no_particle_state_through_the_host(monkeypatch):
    """With the device store the recorded rollout reads no particle state to the host, and the backward
    pass writes only the seed (the loss's dL/dstate) and reads none: the state adjoints go from
    one step's vjp to the next on the device. The host store reads every state and adjoint."""
    moved = {}
    for where in ("device", "host"):
        obj = objective(where)
        mpm = obj.system.mpm
        obj.system.set_state(obj.initial_state)
        calls = {"get": 0, "put": 0}

        def counted(name, f, c=calls):
            return lambda *a: (c.__setitem__(name, c[name] + 1), f(*a))[1]

        monkeypatch.setattr(mpm, "_get_state", counted("get", mpm._get_state))
        monkeypatch.setattr(mpm, "_put_state", counted("put", mpm._put_state))
        monkeypatch.setattr(mpm, "_get", counted("get", mpm._get))  # one key of a state
        monkeypatch.setattr(DeviceState, "__getitem__", counted("get", DeviceState.__getitem__))
        tape = Tape()
        obj.system.rollout(tape=tape)
        forward = dict(calls)
        seed = {"mpm": {k: np.ones_like(v) for k, v in obj.initial_state["mpm"].items()}}
        out = tape.backward(obj.system.vjp, seed)
        moved[where] = (forward, {k: calls[k] - forward[k] for k in calls})
        assert np.all(np.isfinite(out.state0["mpm"]["v"]))
    assert moved["device"] == ({"get": 0, "put": 0}, {"get": 0, "put": 1})
    assert moved["host"][0]["get"] == STEPS + 1  # the state before the first step and after each
    assert moved["host"][1]["get"] == STEPS  # each step's adjoint of the state before it


def test_the_device_store_reuses_freed_buffers_and_frees_them_all():
    """A second gradient evaluation allocates nothing new (the first's buffers came back to the pool), at
    most the states the tape holds plus the last state and two adjoints; with the tape cleared and
    the system's last record dropped no state holds a buffer."""
    obj = objective("device")
    store = obj.system.mpm.checkpoints
    params = obj.initial_params()
    obj.evaluate(params, grad=True)
    first = store.allocated
    assert store.state_bytes * STEPS <= first <= store.state_bytes * (STEPS + 3)
    obj.evaluate(params, grad=True)
    assert store.allocated == first
    obj.tape.clear()
    gc.collect()
    assert store.held == store.state_bytes  # the system's last step record keeps its state before
    obj.system.last = None
    gc.collect()
    assert store.held == 0


def test_a_non_finite_adjoint_on_the_device_is_counted_there_and_named():
    """A NaN in v's adjoint and an inf in F's, copied to the device, are found by the count on the device
    and named by key; the tape's check then stops naming the step and quantity."""
    obj = objective("device")
    mpm = obj.system.mpm
    fields = mpm._adjoint_fields()
    n, d = mpm.n_particles, mpm.dim
    clean = {"x": np.zeros((n, d)), "v": np.zeros((n, d)), "C": np.zeros((n, d, d)), "F": np.zeros((n, d, d))}
    mpm.checkpoints.write(clean, fields, 0)
    assert mpm.checkpoints.read(fields, 0).nonfinite() == []
    bad = dict(clean, v=clean["v"].copy(), F=clean["F"].copy())
    bad["v"][n // 2, 1] = np.nan
    bad["F"][n - 1, 0, 0] = -np.inf
    mpm.checkpoints.write(bad, fields, 0)
    state = mpm.checkpoints.read(fields, 0)
    assert isinstance(state, DeviceState) and state.nonfinite() == ["v", "F"]
    out = {"state": {"mpm": state}, "action": {}, "material": {}}
    with pytest.raises(SimulationError, match=r"dL/d\(mpm.v\) is not finite at macro step 3"):
        _check_finite(out, 3)


def test_the_memory_estimate_says_how_many_checkpoints_the_device_holds():
    """On the CPU the device is the host: all in Taichi arrays. With a budget of 2.5 states the estimate
    says 2 on the device and the rest on the host, and a run allocates exactly those 2."""
    obj = objective("auto")
    estimate = obj.memory_estimate()
    assert estimate.device_budget is None and estimate.on_device == estimate.held_checkpoints
    assert "in Taichi arrays, the host's memory on a CPU" in estimate.describe()
    store = limit_device(obj, 2.5)
    estimate = obj.memory_estimate()
    assert estimate.on_device == 2 and "2 on the x64" in estimate.describe()
    obj.evaluate(obj.initial_params(), grad=True)
    assert store.allocated == estimate.on_device * estimate.checkpoint_bytes


def test_field_bytes_count_an_adjoint_only_where_one_is_allocated():
    """Every Taichi field has a ``grad`` field object; only ``needs_grad`` places it: a gradient engine's
    fields without adjoints (the affine momenta, the bins, the grid box) count once."""
    import taichi as ti

    from cosim.engines.device_memory import taichi_field_bytes

    plain, with_adjoint = ti.field(ti.f64, shape=100), ti.Vector.field(3, ti.f64, shape=100, needs_grad=True)
    assert taichi_field_bytes([plain]) == 800
    assert taichi_field_bytes([with_adjoint]) == 2 * 2400
