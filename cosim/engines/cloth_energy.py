"""Cloth elastic energies (membrane, bending) with JAX derivatives, and their sparse assembly.

Per element, with unit stiffness (the engine scales by k_stretch [N/m] and k_bend [N m]; both
energies are linear in their stiffness, so d(gradient)/dk is the unit gradient):

- membrane (corotated / ARAP), per face:  A ||F - R(F)||^2  [m^2], F = [x1 - x0, x2 - x0] Dm_inv
  (3x2), R its rotational polar factor. From the invariants of C = F^T F (I1 = tr C, J = sqrt det C
  = s1 s2): ||F - R||^2 = s1^2 + s2^2 - 2 (s1 + s2) + 2 = I1 - 2 sqrt(I1 + 2 J) + 2. Guard: both
  square roots get GUARD^2 added under them, so a collapsed face (det C = 0, F = 0) has finite
  derivatives; the change is below 1e-16 relative for any face not collapsed to a line.
- bending (discrete shells), per hinge: w (theta - theta0)^2 [m^0], w = 3 |e|^2 / (A1 + A2) from the
  rest mesh, theta the signed dihedral angle (``hinge_angle``; theta0 its rest value, so curved rest
  shapes rest as they are). Valid for |theta| < pi (a fully folded hinge wraps around).

Gradients in closed form (``membrane_gradient``, ``bending_gradient``; the tests hold them to
``jax.grad`` of the energies), Hessians as ``jax.jacfwd`` of those gradients (the bending one as
2 w (grad theta grad theta^T + (theta - theta0) d(grad theta))), each ``jax.vmap``-ed and jitted,
float64: about twice as fast as ``jax.hessian`` of the energies (forward over reverse mode through
atan2 and the square roots). Assembly: ``SparsePattern`` fixes the CSC structure of a block of the
global Hessian once per mesh and fills it with ``numpy.bincount``.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
# Compiled kernels persist across processes like Taichi's offline cache: the first cloth of a
# process then starts from the cache instead of compiling. JAX's defaults skip kernels that compile
# in under a second or are small, which is all of ours, hence the two thresholds.
if not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
    _cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "cosim" / "jax"
    jax.config.update("jax_compilation_cache_dir", str(_cache))
jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)

import jax.numpy as jnp  # float64 is enabled above, before any array exists
import numpy as np
import scipy.sparse as sp

from cosim.engines.cloth_mesh import ClothMesh

GUARD = 1e-8  # [1] regularises sqrt(det C) and sqrt(I1 + 2J) (see the module docstring)


def membrane_energy(xe: jnp.ndarray, Dm_inv: jnp.ndarray, area: jnp.ndarray) -> jnp.ndarray:
    """A ||F - R(F)||^2 of one face, xe (3, 3) vertex positions [m] (unit stiffness)."""
    F = jnp.stack([xe[1] - xe[0], xe[2] - xe[0]], axis=1) @ Dm_inv
    C = F.T @ F
    I1 = C[0, 0] + C[1, 1]
    J = jnp.sqrt(C[0, 0] * C[1, 1] - C[0, 1] * C[1, 0] + GUARD**2)
    return area * (I1 - 2.0 * jnp.sqrt(I1 + 2.0 * J + GUARD**2) + 2.0)


def membrane_gradient(xe: jnp.ndarray, Dm_inv: jnp.ndarray, area: jnp.ndarray) -> jnp.ndarray:
    """d(membrane_energy)/dxe (3, 3) [m]: with s = sqrt(I1 + 2 J + GUARD^2), dE/dF = A (2 F - 2 (F + dJ/dF) / s)
    and dJ/dF = [C11 f0 - C01 f1, C00 f1 - C01 f0] / J (f0, f1 the columns of F), through F = Ds Dm_inv."""
    F = jnp.stack([xe[1] - xe[0], xe[2] - xe[0]], axis=1) @ Dm_inv
    f0, f1 = F[:, 0], F[:, 1]
    C00, C11, C01 = f0 @ f0, f1 @ f1, f0 @ f1
    J = jnp.sqrt(C00 * C11 - C01 * C01 + GUARD**2)
    s = jnp.sqrt(C00 + C11 + 2.0 * J + GUARD**2)
    dJ = jnp.stack([C11 * f0 - C01 * f1, C00 * f1 - C01 * f0], axis=1) / J
    dDs = area * (2.0 * F - (2.0 / s) * (F + dJ)) @ Dm_inv.T
    return jnp.stack([-dDs[:, 0] - dDs[:, 1], dDs[:, 0], dDs[:, 1]])


def hinge_angle(xe: jnp.ndarray) -> jnp.ndarray:
    """Signed dihedral angle [rad] of hinge (a, b, c, d) (see ``cloth_mesh``): 0 when flat, from the
    normals n1 = e x (c - a) and n2 = (d - a) x e, e = b - a, about the axis e."""
    a, b, c, d = xe
    e = b - a
    n1 = jnp.cross(e, c - a)
    n2 = jnp.cross(d - a, e)
    sin = jnp.dot(jnp.cross(n1, n2), e) / jnp.sqrt(jnp.dot(e, e))
    return jnp.arctan2(sin, jnp.dot(n1, n2))


def hinge_angle_gradient(xe: jnp.ndarray) -> jnp.ndarray:
    """d(hinge_angle)/dxe (4, 3) [rad/m]: the opposite vertices move theta along their face's normal,
    -|e| n1 / |n1|^2 (c) and -|e| n2 / |n2|^2 (d); the edge's ends share those by where c and d project onto
    the edge (t = (p - a).e / |e|^2: b takes -t, a -(1 - t)), so that a translation leaves theta unchanged."""
    a, b, c, d = xe
    e = b - a
    n1 = jnp.cross(e, c - a)
    n2 = jnp.cross(d - a, e)
    e2 = jnp.dot(e, e)
    g_c = -jnp.sqrt(e2) * n1 / jnp.dot(n1, n1)
    g_d = -jnp.sqrt(e2) * n2 / jnp.dot(n2, n2)
    t_c, t_d = jnp.dot(c - a, e) / e2, jnp.dot(d - a, e) / e2
    return jnp.stack([-(1.0 - t_c) * g_c - (1.0 - t_d) * g_d, -t_c * g_c - t_d * g_d, g_c, g_d])


def bending_energy(xe: jnp.ndarray, weight: jnp.ndarray, theta0: jnp.ndarray) -> jnp.ndarray:
    """w (theta - theta0)^2 of one hinge, xe (4, 3) [m] (unit stiffness)."""
    return weight * (hinge_angle(xe) - theta0) ** 2


def bending_gradient(xe: jnp.ndarray, weight: jnp.ndarray, theta0: jnp.ndarray) -> jnp.ndarray:
    """d(bending_energy)/dxe (4, 3) [1/m]."""
    return 2.0 * weight * (hinge_angle(xe) - theta0) * hinge_angle_gradient(xe)


def bending_hessian(xe: jnp.ndarray, weight: jnp.ndarray, theta0: jnp.ndarray) -> jnp.ndarray:
    """d^2(bending_energy)/dxe^2 (4, 3, 4, 3) [1/m^2]."""
    g = hinge_angle_gradient(xe)
    return (
        2.0
        * weight
        * (jnp.einsum("ij,kl->ijkl", g, g) + (hinge_angle(xe) - theta0) * jax.jacfwd(hinge_angle_gradient)(xe))
    )


CHUNK = 512  # elements per jitted call: one compile per process whatever the mesh size


def _pieces(a: np.ndarray) -> list[np.ndarray]:
    """a (n, ...) with its last row repeated up to a whole number of CHUNK rows, in CHUNK-row pieces."""
    padded = np.pad(a, [(0, -len(a) % CHUNK)] + [(0, 0)] * (a.ndim - 1), mode="edge")
    return [padded[s : s + CHUNK] for s in range(0, len(padded), CHUNK)]


class _Elements:
    """Elements of one kind (faces or hinges) of a mesh in ``CHUNK``-row pieces (padded with the last row):
    each piece's vertex indices and its per-element data, put on JAX's device once. ``apply`` runs a
    jitted, vmapped element function piece by piece on the vertices' positions gathered for it; what is
    made once per mesh is not made at each call (padding, the data's conversion), and the gather is
    ``x.take`` (NumPy's ``x[indices]`` with 2D indices is several times slower)."""

    def __init__(self, elements: np.ndarray, *data: np.ndarray) -> None:
        self.n = len(elements)
        self.vertices = _pieces(elements) if self.n else []
        by_piece = zip(*(_pieces(a) for a in data)) if data and self.n else [()] * len(self.vertices)
        self.data = [tuple(jax.device_put(piece) for piece in pieces) for pieces in by_piece]

    def apply(self, batched, x: np.ndarray) -> np.ndarray:
        """batched (a ``_batched`` element function) at positions x (V, 3): (n, ...), one row an element."""
        parts = [np.asarray(batched(x.take(v, axis=0), *d)) for v, d in zip(self.vertices, self.data)]
        return (parts[0] if len(parts) == 1 else np.concatenate(parts))[: self.n]


def _batched(fn):
    """fn vmapped over ``CHUNK`` elements and jitted."""
    return jax.jit(jax.vmap(fn))


_MEMBRANE = tuple(_batched(f) for f in (membrane_energy, membrane_gradient, jax.jacfwd(membrane_gradient)))
_BENDING = tuple(_batched(f) for f in (bending_energy, bending_gradient, bending_hessian))
_ANGLES = _batched(hinge_angle)


def element_dofs(elements: np.ndarray) -> np.ndarray:
    """(n, 3 k) global dof indices 3 v + axis of elements with k vertices each."""
    return (3 * elements[:, :, None] + np.arange(3)).reshape(len(elements), 3 * elements.shape[1])


class ElasticEnergy:
    """Unit-stiffness membrane and bending energies of one mesh, their gradients and element Hessians.

    Arrays in: positions x (V, 3) [m]. Element Hessians come in the order of ``dofs`` (membrane
    faces, then hinges), each row-major over its element's dofs.
    """

    def __init__(self, mesh: ClothMesh) -> None:
        self.mesh = mesh
        self.faces = mesh.faces
        self.hinges = mesh.hinges
        self._faces = _Elements(self.faces, mesh.Dm_inv, mesh.rest_area)
        A = mesh.rest_area[mesh.hinge_faces].sum(axis=1) if len(mesh.hinges) else np.zeros(0)
        e = (
            mesh.vertices[mesh.hinges[:, 1]] - mesh.vertices[mesh.hinges[:, 0]]
            if len(mesh.hinges)
            else np.zeros((0, 3))
        )
        self.hinge_weight = 3.0 * np.einsum("ij,ij->i", e, e) / np.maximum(A, 1e-300)
        self._angles = _Elements(self.hinges)
        self.rest_angle = self.angles(mesh.vertices)
        self._hinges = _Elements(self.hinges, self.hinge_weight, self.rest_angle)
        self.dofs = [element_dofs(self.faces), element_dofs(self.hinges)]

    def angles(self, x: np.ndarray) -> np.ndarray:
        """(H,) [rad] dihedral angle of every hinge at positions x."""
        if len(self.hinges) == 0:
            return np.zeros(0)
        return self._angles.apply(_ANGLES, x)

    def energies(self, x: np.ndarray) -> tuple[float, float]:
        """(membrane, bending) unit-stiffness energies [m^2], [1] at positions x."""
        mem = float(np.sum(self._faces.apply(_MEMBRANE[0], x)))
        if len(self.hinges) == 0:
            return mem, 0.0
        return mem, float(np.sum(self._hinges.apply(_BENDING[0], x)))

    def gradients(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(membrane, bending) unit-stiffness gradients, each (V, 3)."""
        V = len(x)
        g_mem = self._faces.apply(_MEMBRANE[1], x).reshape(-1)
        out = [np.bincount(self.dofs[0].ravel(), g_mem, minlength=3 * V).reshape(V, 3)]
        if len(self.hinges):
            g_bend = self._hinges.apply(_BENDING[1], x).reshape(-1)
            out.append(np.bincount(self.dofs[1].ravel(), g_bend, minlength=3 * V).reshape(V, 3))
        else:
            out.append(np.zeros((V, 3)))
        return out[0], out[1]

    def hessians(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(membrane (F, 9, 9), bending (H, 12, 12)) unit-stiffness element Hessians."""
        H_mem = self._faces.apply(_MEMBRANE[2], x).reshape(len(self.faces), 9, 9)
        if len(self.hinges) == 0:
            return H_mem, np.zeros((0, 12, 12))
        return H_mem, self._hinges.apply(_BENDING[2], x).reshape(len(self.hinges), 12, 12)


def project_psd(H: np.ndarray) -> np.ndarray:
    """Batched symmetric (n, k, k) matrices with negative eigenvalues clamped to zero."""
    if len(H) == 0:
        return H
    w, Q = np.linalg.eigh(H)
    return (Q * np.maximum(w, 0.0)[:, None, :]) @ np.swapaxes(Q, 1, 2)


class SparsePattern:
    """The CSC structure of one block of the global Hessian, built once per mesh and reused.

    ``rows``/``cols`` (n,) give the global (row, col) of every element-Hessian entry in the flat
    order of the concatenated element Hessians; ``row_map``/``col_map`` map global dofs to the
    block's rows/columns (-1: not in the block). With ``diagonal``, the block's diagonal is part of
    the structure so a diagonal (the mass term) can be added in place.
    """

    def __init__(self, rows, cols, row_map, col_map, shape, diagonal: bool = False) -> None:
        r, c = row_map[rows], col_map[cols]
        self.keep = np.flatnonzero((r >= 0) & (c >= 0))
        r, c = r[self.keep], c[self.keep]
        n_diag = min(shape) if diagonal else 0
        r = np.concatenate([r, np.arange(n_diag)])
        c = np.concatenate([c, np.arange(n_diag)])
        key = c.astype(np.int64) * shape[0] + r
        unique, slot = np.unique(key, return_inverse=True)
        self.slot = slot[: len(self.keep)]
        self.diag_slot = slot[len(self.keep) :]
        self.indices = (unique % shape[0]).astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(unique // shape[0], minlength=shape[1]))]).astype(
            np.int32
        )
        self.shape = shape
        self.nnz = len(unique)

    def matrix(self, values: np.ndarray, diagonal: np.ndarray | None = None) -> sp.csc_matrix:
        """The block with summed entries ``values`` (flat, all element entries) plus ``diagonal``."""
        data = np.bincount(self.slot, values[self.keep], minlength=self.nnz)
        if diagonal is not None:
            data[self.diag_slot] += diagonal
        return sp.csc_matrix((data, self.indices, self.indptr), shape=self.shape)


def hessian_entries(dofs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Global (rows, cols) of every entry of the concatenated element Hessians of ``dofs``."""
    rows = np.concatenate([np.repeat(d, d.shape[1], axis=1).ravel() for d in dofs])
    cols = np.concatenate([np.tile(d, (1, d.shape[1])).ravel() for d in dofs])
    return rows, cols
