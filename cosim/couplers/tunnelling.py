"""Particles that went through a rigid body: a check on the contact models' result, per macro step.

A particle went through body b when it is outside b now, on the opposite side from where it was last
seen outside (the outward normals there and now opposed), and was inside b in between: at the start
of this step, or somewhere on its straight path over the step in b's frame (sampled at most
``spacing`` apart). Sliding along a surface, or a particle pushed back out the way it came in, is not
counted; a particle that slips into a thin wall and out of its far side over several steps is.

The check runs on the device, one pass over the particles per step, against the SDFs the contact
models use (the rigid boundary sources'); the host reads a table of counts per soft body and rigid
body, never the particles. On the host, reading the positions twice a step and sampling the SDFs in
numpy took about 10% of a pour_water step (cProfile).
"""

import numpy as np
import taichi as ti

from cosim.engines import field_pool
from cosim.engines.data_oriented import data_oriented

MAX_PATH_SAMPLES = 64  # points at most along one particle's path through a body over a step


@data_oriented
class TunnelWatch:
    """Per rigid body, each particle's outward normal (body frame) where it was last seen outside, and
    the positions the current step started from."""

    def __init__(self, engine, sources: list, spacing: float):
        """``engine``: the MPM engine; ``sources``: its rigid boundary sources (``RigidBoundaries``) in the
        rigid bodies' order; ``spacing`` [m]: the largest step between samples along a path."""
        self.engine = engine
        self.sdfs = [sdf for source in sources for sdf in source.sdfs]
        self.n = len(self.sdfs)
        self.spacing = float(spacing)
        d = engine.dim
        self.x0 = field_pool.vector(self, d, float, shape=engine.capacity)
        self.last_normal = field_pool.vector(self, d, float, shape=(engine.capacity, self.n))
        self.crossed = field_pool.scalar(self, ti.i32, shape=(len(engine.bodies), self.n))  # per soft body, rigid body
        self._kept = -1  # the engine's ``state_version`` whose positions x0 holds

    def reset(self) -> None:
        """Forget where the particles were last seen outside (a new rollout)."""
        self.last_normal.fill(0)

    def begin(self) -> None:
        """Keep the positions the coming step starts from; ``step`` kept them already unless the state
        was set since (a launch less in a plain run)."""
        if self._kept != self.engine.state_version:
            self._remember(self.engine.slot)
            self._kept = self.engine.state_version

    def step(self, poses0: list, poses1: list) -> np.ndarray:
        """(soft bodies, rigid bodies) counts of the particles that went through each rigid body over the
        step since ``begin``, the bodies at ``poses0`` [(position, rotation)] then and ``poses1`` now."""
        d = self.engine.dim
        poses = np.zeros((2, self.n, d + d * d), dtype=self.engine.real)  # one host array (``_watch``)
        for t, at in enumerate((poses0, poses1)):
            for b, (position, rotation) in enumerate(at):
                poses[t, b, :d], poses[t, b, d:] = position, np.reshape(rotation, -1)
        out = np.zeros(self.crossed.shape, dtype=np.int32)
        self._watch(self.engine.slot, poses, out)
        self._kept = self.engine.state_version  # x0 now holds the positions the next step starts from
        return out

    @ti.kernel
    def _remember(self, slot: ti.i32):
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            self.x0[p] = e.x[slot, p]

    @ti.kernel
    def _watch(
        self,
        slot: ti.i32,
        poses: ti.types.ndarray(),
        out: ti.types.ndarray(),
    ):
        """Count the crossings into ``crossed`` and ``out``; ``poses`` (2, bodies, d + d^2): each body's
        position and rotation (row-major) at the step's start (0) and end (1)."""
        e = self.engine
        ti.loop_config(serialize=True)
        for i, j in ti.ndrange(*self.crossed.shape):
            self.crossed[i, j] = 0
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            for b in ti.static(range(self.n)):
                a = self._to_body(self.x0[p], poses, 0, b)
                z = self._to_body(e.x[slot, p], poses, 1, b)
                da, na = self.sdfs[b].distance_normal(a)
                dz, nz = self.sdfs[b].distance_normal(z)
                last = self.last_normal[p, b]
                if da >= 0:
                    last = na
                inside = da < 0
                travel = (z - a).norm()
                flipped = dz >= 0 and last.dot(nz) < 0
                if flipped and not inside and da < travel:  # it may have crossed within the step
                    n = ti.min(MAX_PATH_SAMPLES, ti.max(2, ti.cast(ti.ceil(travel / self.spacing), ti.i32)))
                    for k in range(1, n):
                        if self.sdfs[b].distance(a + (k / n) * (z - a)) < 0:
                            inside = True
                if flipped and inside:
                    ti.atomic_add(self.crossed[e.body_id[p], b], 1)
                if dz >= 0:
                    last = nz
                self.last_normal[p, b] = last
            self.x0[p] = e.x[slot, p]
        ti.loop_config(serialize=True)
        for i, j in ti.ndrange(*self.crossed.shape):  # handed out, not read with to_numpy (a launch more)
            out[i, j] = self.crossed[i, j]

    @ti.func
    def _to_body(self, x, poses: ti.template(), t: ti.template(), b: ti.template()):
        """World point x in the frame of body b at pose t of ``poses`` (position p, rotation R): R^T (x - p)."""
        d = ti.static(self.engine.dim)
        out = ti.Vector.zero(float, d)
        for i in ti.static(range(d)):
            for j in ti.static(range(d)):
                out[i] += poses[t, b, d + d * j + i] * (x[j] - poses[t, b, j])
        return out
