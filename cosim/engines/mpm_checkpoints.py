"""Where a gradient run keeps the MPM states between macro steps: on the engine's device when they fit.

A recorded step hands its state after the step to the tape (the next step's checkpoint), and a step's
``vjp`` hands back the adjoint of the state before it. Read to the host, each is a round trip over the
bus plus two conversions every macro step (float64 for the host, the engine's precision back for the
checkpoint); at 2M particles that is most of a GPU's recorded step. The ``CheckpointStore`` copies them
on the device instead, into Taichi ndarrays in the engine's precision (``DeviceState``), and writes
them back into a particle slot on the device: nothing crosses the bus unless someone reads a key.

Where: ``"device"`` always, ``"host"`` never (float64 numpy arrays, the fallback), ``"auto"`` on the
device while the states held there stay under the device's budget (``device_memory.checkpoint_budget``:
on a CPU the device is the host, no bound), on the host beyond it. A state freed by everyone who held
it (the tape releases checkpoints as the backward pass passes them) gives its buffers back to the
store's pool for the next one: a gradient run allocates at most its peak, once.
"""

import weakref
from collections.abc import Iterator, Mapping

import numpy as np
import taichi as ti

from cosim.engines.device_memory import checkpoint_budget
from cosim.engines.mpm_inputs import STATE_KEYS

WHERE = ("auto", "device", "host")


class DeviceState(Mapping):
    """A particle state (x, v, C, F) or its adjoint held on the device: a read-only mapping that reads a
    key to the host (float64, (N, d) or (N, d, d)) on access. ``CheckpointStore.write`` puts it back into
    a slot without the host."""

    def __init__(self, store: "CheckpointStore", arrays: dict[str, ti.Ndarray]):
        self.store, self.arrays = store, arrays

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in STATE_KEYS:
            raise KeyError(key)
        return self.arrays[key].to_numpy().astype(np.float64)

    def __iter__(self) -> Iterator[str]:
        return iter(STATE_KEYS)

    def __len__(self) -> int:
        return len(STATE_KEYS)

    @property
    def nbytes(self) -> int:
        """Device memory the state holds [bytes]."""
        return self.store.state_bytes

    def nonfinite(self) -> list[str]:
        """The keys holding a NaN or inf: counted on the device, keys read only when there are any."""
        engine = self.store.engine
        if engine._count_nonfinite(*(self.arrays[k] for k in STATE_KEYS)) == 0:
            return []
        return [k for k in STATE_KEYS if not np.all(np.isfinite(self[k]))]


class CheckpointStore:
    """Copies of an MPM engine's particle slots (states or their adjoints) kept on its device while they
    fit the budget, else read to the host; a pool of freed buffers. ``device_bytes`` sets the budget
    of ``where="auto"`` instead of the device's."""

    def __init__(self, engine, where: str = "auto", device_bytes: int | None = None):
        if where not in WHERE:
            raise ValueError(f"checkpoints: '{where}' is not one of {', '.join(WHERE)}")
        self.engine, self.where = engine, where
        self._budget: int | None | bool = False if device_bytes is None else device_bytes  # False: ask the device
        self._free: list[dict[str, ti.Ndarray]] = []
        self.allocated = 0  # [bytes] device buffers made, held or pooled
        self.held = 0  # [bytes] device buffers a state holds

    @property
    def shapes(self) -> dict[str, tuple[int, ...]]:
        return self.engine.state_shapes

    @property
    def state_bytes(self) -> int:
        """Bytes of one state in the engine's precision."""
        return sum(int(np.prod(s)) for s in self.shapes.values()) * np.dtype(self.engine.real).itemsize

    def budget(self) -> int | None:
        """Bytes of states the device may hold (None: no bound): by ``where``, for "auto" ``device_bytes``
        or the device's (``cosim.engines.device_memory.checkpoint_budget``, asked once)."""
        if self.where != "auto":
            return None if self.where == "device" else 0
        if self._budget is False:
            self._budget = checkpoint_budget([self.engine])
        return self._budget

    def read(self, fields: tuple, slot: int) -> "DeviceState | dict[str, np.ndarray]":
        """Slot ``slot`` of ``fields`` (x, v, C, F or their adjoints): a ``DeviceState`` when it fits the
        budget, else read to the host (float64)."""
        arrays = self._take()
        if arrays is None:
            return self.engine._get_state(fields, slot)
        self.engine._copy_state(*fields, slot, *(arrays[k] for k in STATE_KEYS), True)
        state = DeviceState(self, arrays)
        # a weak reference: the registry of finalizers must not hold the store, and through it the engine
        weakref.finalize(state, _give_back, weakref.ref(self), arrays)
        return state

    def write(self, state: Mapping, fields: tuple, slot: int) -> None:
        """Put ``state`` (a ``DeviceState`` of this store, or host arrays by key) into slot ``slot``."""
        if isinstance(state, DeviceState) and state.store is self:
            self.engine._copy_state(*fields, slot, *(state.arrays[k] for k in STATE_KEYS), False)
            return
        values = {k: state[k] for k in STATE_KEYS}  # read first: a host view may read the slot written
        self.engine._put_state(fields, slot, values)

    def _take(self) -> dict[str, ti.Ndarray] | None:
        """A set of buffers from the pool, or new ones within the budget; None when none fits."""
        if self._free:
            arrays = self._free.pop()
        else:
            budget = self.budget()
            if budget is not None and self.allocated + self.state_bytes > budget:
                return None
            dtype = ti.f64 if self.engine.real == np.float64 else ti.f32
            arrays = {k: ti.ndarray(dtype, shape) for k, shape in self.shapes.items()}
            self.allocated += self.state_bytes
        self.held += self.state_bytes
        return arrays


def _give_back(store_ref: weakref.ref, arrays: dict[str, ti.Ndarray]) -> None:
    """A freed state's buffers back to its store's pool (dropped with them if the store is gone)."""
    store = store_ref()
    if store is not None:
        store.held -= store.state_bytes
        store._free.append(arrays)
