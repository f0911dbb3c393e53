"""Copies between the MPM's particle slots and the host: ``SlotIO``, a base of ``MPMKernels``.

Its kernels read the engine's particle fields (``x``, ``v``, ``C``, ``F`` and their adjoints, or any
per-particle field given), ``count``, ``n_particles``, ``dim``, ``real`` and ``serial_particle_loops``.
They loop over the particle count, not the fields' capacity (``mpm_inputs.particle_capacity``).
"""

from collections.abc import Mapping

import numpy as np
import taichi as ti

from cosim.engines.data_oriented import data_oriented
from cosim.engines.mpm_inputs import STATE_KEYS
from cosim.engines.mpm_watch import non_finite


@data_oriented
class SlotIO:
    """Slot copies on the device, and reads / writes of one slot of a particle field from / to the host."""

    @ti.kernel
    def _copy_slot(self, src: ti.i32, dst: ti.i32):
        ti.loop_config(serialize=self.serial_particle_loops)
        for p in range(self.count[None]):
            self.x[dst, p] = self.x[src, p]
            self.v[dst, p] = self.v[src, p]
            self.C[dst, p] = self.C[src, p]
            self.F[dst, p] = self.F[src, p]

    @ti.kernel
    def _read_slot(self, fld: ti.template(), slot: ti.i32, out: ti.types.ndarray()):
        """Copy one slot of a particle field (or its adjoint) into out (n, d) or (n, d, d)."""
        ti.loop_config(serialize=self.serial_particle_loops)
        for p in range(self.count[None]):
            if ti.static(fld.m == 1):
                for i in ti.static(range(fld.n)):
                    out[p, i] = fld[slot, p][i]
            else:
                for i, j in ti.static(ti.ndrange(fld.n, fld.m)):
                    out[p, i, j] = fld[slot, p][i, j]

    @ti.kernel
    def _copy_state(
        self,
        x: ti.template(),
        v: ti.template(),
        C: ti.template(),
        F: ti.template(),
        slot: ti.i32,
        ax: ti.types.ndarray(),
        av: ti.types.ndarray(),
        aC: ti.types.ndarray(),
        aF: ti.types.ndarray(),
        to_arrays: ti.template(),
    ):
        """Copy slot ``slot`` of x, v, C, F (or their adjoints) into arrays (n, d) and (n, d, d)
        (``to_arrays``), or the arrays into the slot: device arrays (checkpoints) or host ones."""
        ti.loop_config(serialize=self.serial_particle_loops)
        for p in range(self.count[None]):
            for i in ti.static(range(self.dim)):
                if ti.static(to_arrays):
                    ax[p, i], av[p, i] = x[slot, p][i], v[slot, p][i]
                else:
                    x[slot, p][i], v[slot, p][i] = ax[p, i], av[p, i]
                for j in ti.static(range(self.dim)):
                    if ti.static(to_arrays):
                        aC[p, i, j], aF[p, i, j] = C[slot, p][i, j], F[slot, p][i, j]
                    else:
                        C[slot, p][i, j], F[slot, p][i, j] = aC[p, i, j], aF[p, i, j]

    @ti.kernel
    def _count_nonfinite(
        self, x: ti.types.ndarray(), v: ti.types.ndarray(), C: ti.types.ndarray(), F: ti.types.ndarray()
    ) -> ti.i32:
        """How many entries of the four device arrays are NaN or infinite."""
        bad = 0
        ti.loop_config(serialize=self.serial_particle_loops)
        for p in range(self.count[None]):
            for i in ti.static(range(self.dim)):
                bad += ti.cast(non_finite(x[p, i]), ti.i32) + ti.cast(non_finite(v[p, i]), ti.i32)
                for j in ti.static(range(self.dim)):
                    bad += ti.cast(non_finite(C[p, i, j]), ti.i32) + ti.cast(non_finite(F[p, i, j]), ti.i32)
        return bad

    @ti.kernel
    def _write_vectors(self, fld: ti.template(), src: ti.types.ndarray()):
        """Copy src (n, d) into a per-particle vector field (the controls): Taichi's ``from_numpy`` is a
        parallel loop over the whole capacity."""
        ti.loop_config(serialize=self.serial_particle_loops)
        for p in range(self.count[None]):
            for i in ti.static(range(fld.n)):
                fld[p][i] = src[p, i]

    def _get(self, fld, slot: int) -> np.ndarray:
        shape = (self.n_particles, self.dim) if fld.m == 1 else (self.n_particles, self.dim, self.dim)
        out = np.empty(shape, dtype=self.real)
        self._read_slot(fld, slot, out)
        return out.astype(np.float64)

    @property
    def state_shapes(self) -> dict[str, tuple[int, ...]]:
        """The shapes of one state's arrays by ``STATE_KEYS``: x, v (n, d), C, F (n, d, d)."""
        n, d = self.n_particles, self.dim
        return {"x": (n, d), "v": (n, d), "C": (n, d, d), "F": (n, d, d)}

    def _get_state(self, fields: tuple, slot: int) -> dict[str, np.ndarray]:
        """Slot ``slot`` of x, v, C, F (or their adjoints: ``fields``) on the host, float64, in one launch of
        ``_copy_state``, where a read per field compiled a kernel per field and launched four."""
        arrays = {k: np.empty(shape, dtype=self.real) for k, shape in self.state_shapes.items()}
        self._copy_state(*fields, slot, *arrays.values(), True)
        return {k: a.astype(np.float64) for k, a in arrays.items()}

    def _put_state(self, fields: tuple, slot: int, values: Mapping[str, np.ndarray]) -> None:
        """Write host arrays ``values`` (by ``STATE_KEYS``) into slot ``slot`` of ``fields`` (one launch)."""
        arrays = {k: np.ascontiguousarray(values[k], dtype=self.real) for k in STATE_KEYS}
        self._copy_state(*fields, slot, *arrays.values(), False)
