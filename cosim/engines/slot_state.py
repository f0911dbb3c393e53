"""A particle state left on the device: the MPM's per-step state without a host copy nobody reads.

A forward-only MPM step hands out its states (the record's state before, the outputs' state after) as
``SlotState``: a read-only mapping of the state keys (x, v, C, F) that reads a key from its particle slot
on first access, as float64 (N, d) or (N, d, d), and caches it. The engine keeps a slot untouched until a
later step writes it (``MPMEngine`` rotates three slots), so a key can be read until then; after that,
reading it raises instead of returning another step's numbers.
"""

from collections.abc import Iterator, Mapping

import numpy as np

from cosim.engines.mpm_kernels import STATE_KEYS


class SlotState(Mapping):
    """The particle state in slot ``slot`` of ``engine`` as it is now, read key by key on first access."""

    def __init__(self, engine, slot: int):
        self._engine, self._slot = engine, slot
        self._version = engine.slot_version(slot)
        self._read: dict[str, np.ndarray] = {}

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in self._read:
            if key not in STATE_KEYS:
                raise KeyError(key)
            if self._engine.slot_version(self._slot) != self._version:
                raise RuntimeError(
                    f"MPM state key '{key}' read after the engine overwrote those particles: a forward step's "
                    "record.state lasts until the next step, its outputs' state until the one after; read the "
                    "keys needed (or dict(state)) before"
                )
            self._read[key] = self._engine.read_slot(key, self._slot)
        return self._read[key]

    def __iter__(self) -> Iterator[str]:
        return iter(STATE_KEYS)

    def __len__(self) -> int:
        return len(STATE_KEYS)
