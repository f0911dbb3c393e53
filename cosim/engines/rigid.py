"""DART rigid bodies with a one-step vector-Jacobian product, for coupling to the differentiable MPM.

Layouts (fixed at construction; skeletons in the order given, dofs in DART's skeleton order):
- state: ``[q_0, q_1, ..., qd_0, qd_1, ...]``, all positions of all skeletons, then all velocities
  (length 2 * ``dofs``). Free joint: q = [rotation vector, translation] of the body relative to the joint
  origin, qd = [angular, linear] velocity of the body origin (world frame for a root free joint); ball joint:
  q = rotation vector, qd = angular velocity in the child body frame; planar: [x, y, angle about z].
- action: per skeleton, per joint in DART's joint order, the block of every joint whose control mode is not
  ``passive``: torque/velocity -> one entry per dof; wrench/twist -> 6 ([torque; force] or [angular; linear],
  world frame, about/of the body origin). ``action_layout`` lists the blocks.
- wrenches: (len(body_names), 6) rows [torque; force] in world coordinates, torque about the BODY ORIGIN (the
  body frame's origin, not the COM), applied for one step.
- bodies: ``body_names`` = "skeleton/link" for every body node, skeletons in order, DART's body order within.

The step is DART's: semi-implicit Euler, implicit joint damping, enforced joint limits, optional rigid contact
(Bullet) between skeletons with ``collide`` and with an optional static ``ground`` (``GroundSpec``; not a
skeleton of the state: no dofs, no body name). DART resolves a contact's penetration at no more than 1 mm/s
(its contact error reduction, not settable from Python): a body that lands at speed v sinks up to v dt in the
landing step and rises back to the surface at 1 mm/s. ``vjp`` differentiates one step (``rigid_adjoint``).
"""

from __future__ import annotations

from dataclasses import dataclass

import dartpy as dart
import numpy as np

from cosim.engines import rigid_added_mass
from cosim.engines.rigid_adjoint import RigidAdjoint, StepRecord
from cosim.engines.rigid_build import (
    CONTROL_MODES,
    GroundSpec,
    ShapeSpec,
    SkeletonSpec,
    build_ground,
    build_skeleton,
    urdf_geometry,
)
from cosim.errors import InputError, SimulationError

_ORIGIN = np.zeros(3)
_ADDITIVE = ("RevoluteJoint", "PrismaticJoint")  # q' = q + dt qd': a velocity bound keeps q' inside limits
CONSTRAINT_TOL = 1e-9  # [N or N m] a generalised constraint force above this means a limit or contact acted


@dataclass
class Control:
    """One controlled joint: skeleton index, DART joint, skeleton-local dof indices, mode, action slice."""

    skel: int
    joint: object
    dofs: np.ndarray
    mode: str
    slice: slice
    limits: tuple[np.ndarray, np.ndarray] | None = None  # velocity mode: enforced position limits of its dofs


# ------------------------------------------------------------------------------------------------ engine


class RigidEngine(RigidAdjoint):
    """One DART world holding the given skeletons (deactivation off, so replay from a state is bitwise),
    and ``ground``, a static floor the colliding skeletons rest on (needs ``collision``)."""

    capabilities = frozenset({"points", "body_states", "energy"})

    def __init__(
        self,
        skeleton_specs: list[SkeletonSpec],
        dt: float,
        gravity=(0.0, 0.0, -9.81),
        collision: bool = True,
        ground: GroundSpec | None = None,
    ) -> None:
        if ground is not None and not collision:
            raise InputError("a rigid ground needs collision on (nothing would touch it)")
        names = [s.name for s in skeleton_specs]
        if len(set(names)) != len(names):
            raise InputError(f"skeleton names must be unique, got {names}")
        self.specs = list(skeleton_specs)
        self.world = dart.simulation.World()
        self.set_time_step(dt)
        self.world.setGravity(np.asarray(gravity, dtype=np.float64))
        options = self.world.getDeactivationOptions()
        options.mEnabled = False
        self.world.setDeactivationOptions(options)
        # Bullet: FCL in this wheel has no capsule and lets cylinders sink; Bullet handles all five shape kinds.
        self.world.getConstraintSolver().setCollisionDetector(dart.collision.BulletCollisionDetector())
        self.skeletons = [build_skeleton(s) for s in self.specs]
        for spec, skel in zip(self.specs, self.skeletons):
            self.world.addSkeleton(skel)
            for body in skel.getBodyNodes():
                body.setCollidable(bool(collision and spec.collide))
        if ground is not None:
            self.world.addSkeleton(build_ground(ground))
        sizes = [s.getNumDofs() for s in self.skeletons]
        self._offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self.dofs = int(self._offsets[-1])
        self._bodies = [(k, b) for k, s in enumerate(self.skeletons) for b in s.getBodyNodes()]
        self.body_names = [f"{self.specs[k].name}/{b.getName()}" for k, b in self._bodies]
        self.controls = self._parse_controls()
        driven = {c.skel for c in self.controls}
        self._passive_skeletons = [k for k in range(len(self.skeletons)) if k not in driven]  # energy budget
        self._passive = np.array([k not in driven for k, _body in self._bodies], dtype=bool)
        self.action_size = sum(c.slice.stop - c.slice.start for c in self.controls)
        self._kinematic = self._kinematic_masks()
        self._rotation_blocks = self._find_rotation_blocks()
        self.steps = 0
        self._known_bodies: tuple[bytes, dict] | None = None  # (flat state's bytes, body_states() there)

    # ------------------------------------------------------------------------------------- construction

    def set_time_step(self, dt: float) -> None:
        """Step ``dt`` [s] from now on (a scene builds it with the frame over its exchanges, ``Stepping``)."""
        if not dt > 0:
            raise InputError(f"rigid dt must be > 0, got {dt}")
        self.dt = float(dt)
        self.world.setTimeStep(self.dt)

    def _parse_controls(self) -> list[Control]:
        """Controls in action order; sets DART VELOCITY actuators on velocity/twist joints."""
        controls, start = [], 0
        for k, (spec, skel) in enumerate(zip(self.specs, self.skeletons)):
            joints = {j.getName(): j for j in skel.getJoints()}
            unknown = sorted(set(spec.controls) - set(joints))
            if unknown:
                raise InputError(
                    f"skeleton '{spec.name}': controls name unknown joints {unknown}; joints: {sorted(joints)}"
                )
            for name, joint in joints.items():
                mode = spec.controls.get(name, spec.default_control)
                where = f"skeleton '{spec.name}', joint '{name}'"
                _check_mode(mode, joint, where)
                n = joint.getNumDofs()
                if mode == "passive" or n == 0:
                    continue
                if mode in ("velocity", "twist"):
                    joint.setActuatorType(dart.dynamics.ActuatorType.VELOCITY)
                size = 6 if mode in ("wrench", "twist") else n
                dofs = np.array([joint.getIndexInSkeleton(i) for i in range(n)])
                limits = None
                if mode == "velocity" and joint.areLimitsEnforced() and joint.getType() in _ADDITIVE:
                    limits = (np.asarray(joint.getPositionLowerLimits()), np.asarray(joint.getPositionUpperLimits()))
                controls.append(Control(k, joint, dofs, mode, slice(start, start + size), limits))
                start += size
        return controls

    def _kinematic_masks(self) -> list[np.ndarray]:
        masks = [np.zeros(s.getNumDofs(), dtype=bool) for s in self.skeletons]
        for c in self.controls:
            if c.mode in ("velocity", "twist"):
                masks[c.skel][c.dofs] = True
        return masks

    def _find_rotation_blocks(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """(type, global dof indices, origin rotation) of free/ball joints; all others integrate q += dt qd."""
        blocks = []
        for k, skel in enumerate(self.skeletons):
            for joint in skel.getJoints():
                kind = joint.getType()
                if kind in ("FreeJoint", "BallJoint"):
                    idx = [self._offsets[k] + joint.getIndexInSkeleton(i) for i in range(joint.getNumDofs())]
                    R0 = joint.getTransformFromParentBodyNode().rotation()
                    blocks.append((kind, np.array(idx), np.asarray(R0)))
                elif kind not in ("RevoluteJoint", "PrismaticJoint", "PlanarJoint", "WeldJoint"):
                    raise InputError(f"skeleton '{skel.getName()}': joint type {kind} is not supported")
        return blocks

    @property
    def action_layout(self) -> list[tuple[str, str, str, slice]]:
        """(skeleton, joint, mode, slice into the action) for every action block."""
        return [(self.specs[c.skel].name, c.joint.getName(), c.mode, c.slice) for c in self.controls]

    # ------------------------------------------------------------------------------------------- state

    def flat_state(self) -> np.ndarray:
        """All positions, then all velocities (see the module docstring)."""
        q = [s.getPositions() for s in self.skeletons]
        qd = [s.getVelocities() for s in self.skeletons]
        return np.concatenate(q + qd) if self.dofs else np.zeros(0)

    def set_flat_state(self, s: np.ndarray) -> None:
        """Restore a ``flat_state()``; stepping from it again is bitwise identical."""
        s = np.asarray(s, dtype=np.float64)
        if s.shape != (2 * self.dofs,):
            raise InputError(f"rigid state must have length {2 * self.dofs} (positions then velocities), got {s.shape}")
        n, o = self.dofs, self._offsets
        for k, skel in enumerate(self.skeletons):
            skel.setPositions(s[o[k] : o[k + 1]])
            skel.setVelocities(s[n + o[k] : n + o[k + 1]])

    # ------------------------------------------------------------------------------------- the contract

    name = "dart"

    def state(self) -> dict[str, np.ndarray]:
        """``q`` (dofs,) joint positions and ``qd`` (dofs,) joint velocities, skeletons in order."""
        s = self.flat_state()
        return {"q": s[: self.dofs], "qd": s[self.dofs :]}

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore a ``state()``; stepping from it again is bitwise identical."""
        self.set_flat_state(np.concatenate([state["q"], state["qd"]]))

    def step(self, inputs: dict) -> tuple[dict, StepRecord]:
        """One step of dt under ``inputs`` action (action_size,) (None: zeros), forces: per-body wrenches
        (len(body_names), 6) [torque; force] in the world frame, torque about the body origin (None: zeros) and
        added_mass (len(body_names), 6, 6) (None: none; ``rigid_added_mass``). Returns ({state}, record)."""
        record = self.advance(inputs.get("action"), inputs.get("forces"), inputs.get("added_mass"))
        n = self.dofs
        return {"state": {"q": record.next_state[:n], "qd": record.next_state[n:]}}, record

    def vjp(self, record: StepRecord, grad_outputs: dict) -> dict:
        """{"state": dL/d(state after)} -> dL/d(state before), dL/d(action), dL/d(forces) and, where the step
        had one, dL/d(added_mass) (see ``vjp_flat``)."""
        g = grad_outputs["state"]
        grads = self.vjp_flat(record, np.concatenate([g["q"], g["qd"]]))
        n = self.dofs
        out = {"state": {"q": grads[0][:n], "qd": grads[0][n:]}, "action": grads[1], "forces": grads[2]}
        if record.added is not None:
            out["added_mass"] = grads[3]
        return out

    def parameters(self) -> list:
        """The action sequence, when any joint is controlled."""
        from cosim.engines.contract import Parameter

        return [Parameter("action", self.name, "input", "action", 1e-3)] if self.action_size else []

    # -------------------------------------------------------------------------------------------- step

    def advance(self, action: np.ndarray | None = None, wrenches: np.ndarray | None = None, added=None) -> StepRecord:
        """Advance one dt under the action, per-body world wrenches and added masses; NaN -> SimulationError."""
        action, wrenches = self._check_inputs(action, wrenches)
        added = rigid_added_mass.check_added_mass(added, len(self._bodies))
        before = self.flat_state()
        clamped = self._apply(action, wrenches)
        self.world.step()
        if added is not None:
            self._step_with_added_mass(before, action, wrenches, added)
        self.steps += 1
        after = self.flat_state()
        self._check_finite(after)
        return StepRecord(before, action, wrenches, after, self.steps, clamped, self._active_constraint(), added)

    def _step_with_added_mass(self, before: np.ndarray, action, wrenches, added: np.ndarray) -> None:
        """Redo the step just taken from ``before`` so that the bodies' added masses join their inertia
        (``cosim.engines.rigid_added_mass``: the second of its two DART steps)."""
        n = self.dofs
        change = self.flat_state()[n:] - before[n:]
        self.set_flat_state(before)
        jacobians = rigid_added_mass.body_jacobians(self, added)
        change = rigid_added_mass.corrected_change(self, added, change, jacobians)
        self._apply(action, wrenches + rigid_added_mass.extra_wrenches(self, added, change, jacobians))
        self.world.step()

    def _active_constraint(self) -> tuple[str, float] | None:
        """("skeleton/dof", force) of the last step's largest generalised constraint force (a joint limit or a
        rigid contact acted), or None."""
        for spec, skel in zip(self.specs, self.skeletons):
            forces = np.asarray(skel.getConstraintForces())
            if len(forces) and np.abs(forces).max() > CONSTRAINT_TOL:
                i = int(np.argmax(np.abs(forces)))
                return f"{spec.name}/{skel.getDof(i).getName()}", float(forces[i])
        return None

    def _check_inputs(self, action, wrenches) -> tuple[np.ndarray, np.ndarray]:
        action = np.zeros(self.action_size) if action is None else np.asarray(action, dtype=np.float64).reshape(-1)
        if action.size != self.action_size:
            layout = ", ".join(f"{s}/{j}:{m}[{sl.start}:{sl.stop}]" for s, j, m, sl in self.action_layout)
            raise InputError(
                f"rigid action has length {action.size}, expected {self.action_size} ({layout or 'no controls'})"
            )
        nb = len(self._bodies)
        wrenches = np.zeros((nb, 6)) if wrenches is None else np.asarray(wrenches, dtype=np.float64)
        if wrenches.shape != (nb, 6):
            raise InputError(
                f"rigid wrenches must have shape ({nb}, 6) = (bodies, [torque; force]), got {wrenches.shape}"
            )
        if not (np.all(np.isfinite(action)) and np.all(np.isfinite(wrenches))):
            raise InputError("rigid action or wrenches contain non-finite values (DART would silently drop them)")
        return action, wrenches

    def _joint_jacobian(self, c: Control) -> np.ndarray:
        """World Jacobian of the joint's child body origin w.r.t. the joint's own dofs (6 x 6 for a free root)."""
        return self._body_jacobian(c.skel, c.joint.getChildBodyNode())[:, c.dofs]

    def _body_jacobian(self, k: int, body) -> np.ndarray:
        """6 x (dofs of skeleton k) world Jacobian of the body origin, rows [angular; linear]."""
        return self.skeletons[k].getWorldJacobian(body, _ORIGIN)

    def _apply(self, action: np.ndarray, wrenches: np.ndarray) -> np.ndarray:
        """Set joint forces, velocity commands and external wrenches for the next world.step(). DART does
        not enforce position limits on velocity-actuated joints, so a velocity command is clipped to
        what keeps q + dt qd inside the limits; returns which action entries were clipped."""
        taus = [np.zeros(s.getNumDofs()) for s in self.skeletons]
        commands = []
        clamped = np.zeros(self.action_size, dtype=bool)
        for c in self.controls:
            a = action[c.slice]
            if c.mode == "torque":
                taus[c.skel][c.dofs] += a
            elif c.mode == "wrench":
                taus[c.skel][c.dofs] += self._joint_jacobian(c).T @ a
            else:
                target = a if c.mode == "velocity" else np.linalg.solve(self._joint_jacobian(c), a)
                if c.limits is not None:
                    q = self.skeletons[c.skel].getPositions()[c.dofs]
                    bounded = np.clip(target, (c.limits[0] - q) / self.dt, (c.limits[1] - q) / self.dt)
                    clamped[c.slice] = bounded != target
                    target = bounded
                commands.append((c, target))
        for skel, tau in zip(self.skeletons, taus):
            skel.setForces(tau)
        for c, target in commands:
            for d, v in zip(c.dofs, target):
                self.skeletons[c.skel].setCommand(int(d), float(v))
        for (k, body), w in zip(self._bodies, wrenches):
            if np.any(w):
                body.addExtTorque(w[:3], False)
                body.addExtForce(w[3:], _ORIGIN, False, True)
        return clamped

    def _advance(self, state: np.ndarray, action: np.ndarray, wrenches: np.ndarray, added=None) -> np.ndarray:
        """The step from a given state, without bookkeeping (for finite differences)."""
        self.set_flat_state(state)
        self._apply(action, wrenches)
        self.world.step()
        if added is not None:
            self._step_with_added_mass(state, action, wrenches, added)
        return self.flat_state()

    def _check_finite(self, s: np.ndarray) -> None:
        n, o = self.dofs, self._offsets
        for k, spec in enumerate(self.specs):
            if not (np.all(np.isfinite(s[o[k] : o[k + 1]])) and np.all(np.isfinite(s[n + o[k] : n + o[k + 1]]))):
                raise SimulationError(
                    f"rigid skeleton '{spec.name}' has a non-finite state after step {self.steps}; "
                    "reduce dt, add joint damping or check the applied forces"
                )

    # ------------------------------------------------------------------------------ energy budget
    def energy_and_mass(self) -> tuple[float, float]:
        """(kinetic + potential energy [J] (gravity, joint springs: DART's), mass [kg]) of the skeletons no
        action drives; a driven skeleton's energy is the actions' business, its contacts' work external."""
        passive = [self.skeletons[k] for k in self._passive_skeletons]
        energy = sum(s.computeKineticEnergy() + s.computePotentialEnergy() for s in passive)
        return float(energy), float(sum(s.getMass() for s in passive))

    def has_free_dofs(self, body: int) -> bool:
        """Whether body ``body``'s skeleton has dofs no velocity command prescribes (forces move them)."""
        return bool((~self._kinematic[self._bodies[body][0]]).any())

    def passive_bodies(self) -> np.ndarray:
        """(len(body_names),) bool: bodies of skeletons no action drives (in the energy budget)."""
        return self._passive.copy()

    def external_work(self, record) -> float:
        """[J] Work done on the budgeted skeletons by their own actions in the recorded step: none."""
        return 0.0

    def points(self) -> np.ndarray:
        """(n, 3) [m] the origins of the bodies no action drives, which must stay in the MPM's domain if they start
        in it (one that leaves was flung by what it touches; a driven body goes where its actions take it)."""
        return self.body_states()["position"][self._passive]

    def point_name(self, i: int) -> str:
        return f"body '{np.asarray(self.body_names)[self._passive][i]}'"

    def body_states(self) -> dict[str, np.ndarray]:
        """Per body (``body_names`` order), world frame: ``position`` of the body origin (nb, 3), ``rotation``
        body-to-world (nb, 3, 3), ``linear_velocity`` of the origin (nb, 3), ``angular_velocity`` (nb, 3)."""
        key = self.flat_state().tobytes()  # they are a function of the state: computed once per state
        if self._known_bodies is None or self._known_bodies[0] != key:
            self._known_bodies = (key, self._body_states_now())
        return {name: values.copy() for name, values in self._known_bodies[1].items()}

    def _body_states_now(self) -> dict[str, np.ndarray]:
        """``body_states`` from DART (a transform and a Jacobian per body, each a Python call into DART: a
        coupled step asks four times, for the CFL speed, the tunnelling poses and the boundary)."""
        nb = len(self._bodies)
        out = {
            "position": np.zeros((nb, 3)),
            "rotation": np.zeros((nb, 3, 3)),
            "linear_velocity": np.zeros((nb, 3)),
            "angular_velocity": np.zeros((nb, 3)),
        }
        qds = [s.getVelocities() for s in self.skeletons]
        for i, (k, body) in enumerate(self._bodies):
            T = body.getWorldTransform().matrix()
            twist = self._body_jacobian(k, body) @ qds[k]
            out["position"][i], out["rotation"][i] = T[:3, 3], T[:3, :3]
            out["angular_velocity"][i], out["linear_velocity"][i] = twist[:3], twist[3:]
        return out

    # --------------------------------------------------------------------------------------- geometry

    def dof_indices(self, skeleton: str, joint: str) -> np.ndarray:
        """Indices into the positions block of ``state()`` (add ``dofs`` for velocities) of a joint's dofs."""
        names = [s.name for s in self.specs]
        if skeleton not in names:
            raise InputError(f"no skeleton '{skeleton}'; skeletons: {names}")
        k = names.index(skeleton)
        joints = {j.getName(): j for j in self.skeletons[k].getJoints()}
        if joint not in joints:
            raise InputError(f"skeleton '{skeleton}' has no joint '{joint}'; joints: {sorted(joints)}")
        j = joints[joint]
        return np.array([self._offsets[k] + j.getIndexInSkeleton(i) for i in range(j.getNumDofs())], dtype=int)

    def body_index(self, name: str) -> int:
        """Index in ``body_names`` of "skeleton/link" or of a link name unique across skeletons."""
        if name in self.body_names:
            return self.body_names.index(name)
        hits = [i for i, full in enumerate(self.body_names) if full.split("/", 1)[1] == name]
        if len(hits) != 1:
            raise InputError(f"rigid body '{name}' is {'ambiguous' if hits else 'unknown'}; bodies: {self.body_names}")
        return hits[0]

    def welded_parent(self, index: int) -> int | None:
        """Index of the body that body ``index`` is welded to (a fixed joint), or None."""
        k, body = self._bodies[index]
        parent = body.getParentBodyNode()
        if parent is None or body.getParentJoint().getType() != "WeldJoint":
            return None
        return next(i for i, (j, b) in enumerate(self._bodies) if j == k and b.getName() == parent.getName())

    def body_transform(self, index: int) -> np.ndarray:
        """The 4x4 world transform of body ``index`` now."""
        return np.asarray(self._bodies[index][1].getWorldTransform().matrix(), dtype=np.float64)

    def link_geometry(self, body_name: str) -> list[tuple[ShapeSpec, np.ndarray]]:
        """Collision shapes of a body with their 4x4 pose in the body frame (mesh paths absolute)."""
        k, body = self._bodies[self.body_index(body_name)]
        spec = self.specs[k]
        if spec.urdf is not None:
            shapes = urdf_geometry(spec).get(body.getName(), [])
        else:
            shapes = next(link.shapes for link in spec.links if link.name == body.getName())
        return [(s, s.transform()) for s in shapes]


def _check_mode(mode: str, joint, where: str) -> None:
    if mode not in CONTROL_MODES:
        raise InputError(f"{where}: unknown control mode '{mode}'; use one of {', '.join(CONTROL_MODES)}")
    if mode in ("wrench", "twist") and (joint.getType() != "FreeJoint" or joint.getParentBodyNode() is not None):
        raise InputError(
            f"{where}: '{mode}' control needs a free joint attached to the world; use 'torque' or 'velocity'"
        )
