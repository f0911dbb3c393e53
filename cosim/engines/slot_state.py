"""A particle state left on the device: the MPM's per-step state without a host copy nobody reads.

A forward-only MPM step hands out its states (the record's state before, the outputs' state after) as
``SlotState``: a read-only mapping of the state keys (x, v, C, F) that reads a key from its particle slot
on first access, as float64 (N, d) or (N, d, d), and caches it. Before the engine overwrites a slot it
``detach``es the views of it that are still referenced (reads their remaining keys), so a view holds its
step's numbers for as long as anyone keeps it; the coupled loop drops its views before the engine
overwrites them (``MPMEngine`` rotates four slots), so nothing is read that nobody asked for.
"""

from collections.abc import Iterator, Mapping

import numpy as np

from cosim.engines.mpm_inputs import STATE_KEYS


class SlotState(Mapping):
    """The particle state in slot ``slot`` of ``engine`` as it is now, read key by key on first access."""

    def __init__(self, engine, slot: int):
        self._engine, self._slot = engine, slot
        self._read: dict[str, np.ndarray] = {}

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in self._read:
            if key not in STATE_KEYS:
                raise KeyError(key)
            self._read[key] = self._engine.read_slot(key, self._slot)
        return self._read[key]

    def detach(self) -> None:
        """Read every key not read yet, in one launch if more than one (on a GPU each read is a wait): the
        engine is about to overwrite the slot."""
        missing = [key for key in STATE_KEYS if key not in self._read]
        if len(missing) > 1:
            state = self._engine.read_slot(None, self._slot)
            self._read.update({key: state[key] for key in missing})
        for key in missing:
            self[key]
        self._engine = None

    def __iter__(self) -> Iterator[str]:
        return iter(STATE_KEYS)

    def __len__(self) -> int:
        return len(STATE_KEYS)
