"""The body the command gate knows: Prime's collision geometry, and whether a commanded pose brings two of its
bodies closer than the margin.

The geometry is the robot's MuJoCo model (``config.model``): the capsules, boxes and cylinders of the two arms, the
torso, its base and the pedestal, in three classes (the left arm, the right arm, the body). The pairs checked are
the pairs MuJoCo itself collides: geoms of different classes whose bodies are not excluded (a shoulder and the
torso it sits on), so the gate refuses what the simulation would show as a contact, ``margin`` early. The distance
is MuJoCo's own (``mj_geomDistance``), on a private model and data, called from the compiled kernel
(``_tick.BodyKernel``) with no Python between the kinematics and the distances.

A pose is the commanded target where a joint has one (a finite position with stiffness above zero), and the
measured position where it does not (no command, a limp or damped joint). A target is taken ``stopping_time``
further along the joint's measured velocity: a moving arm does not stop on its target at once, and the gate refuses
the pose where it comes to rest. No joint goes beyond its stops: a pose is clipped to them. A joint whose position
is unknown (not measured and no target, or its frame unknown: a joint being calibrated) takes every body it
carries out of the check: the check covers the bodies whose place it knows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import numpy.typing as npt

from humanoid_prime.config.model import load_model
from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import BodyKernel
from humanoid_prime.control.interfaces import Frame
from humanoid_prime.errors import PrimeError

# The classes of prime.xml's contype bits (config.model).
GROUPS = {1: "left arm", 2: "right arm", 4: "body"}
CLOSING_TOLERANCE_M = 1e-4  # a pair is closing when the command brings it nearer than it is by more than this
FAR_M = 10.0  # farther than any two bodies of the robot: a distance asked up to this is the distance


@dataclass(frozen=True)
class Contact:
    """Two bodies of the robot closer than the margin: their names, their classes and MuJoCo's distance (m)."""

    body1: str
    body2: str
    group1: str
    group2: str
    distance: float

    def words(self, margin: float) -> str:
        return f"{self.body1} and {self.body2} {self.distance:.3f} m apart (margin {margin:.3f} m)"


def mujoco_library() -> bytes:
    """The path of the MuJoCo C library the ``mujoco`` package loads (the kernel calls into it)."""
    folder = Path(mujoco.__file__).parent
    found = sorted(folder.glob("libmujoco.so*")) + sorted(folder.glob("libmujoco*.dylib"))
    if not found:
        raise PrimeError(f"MuJoCo's C library is not in {folder} (libmujoco.so*): reinstall the mujoco package")
    return str(found[0]).encode()


class BodyCheck:
    """The collision geometry of ``robot`` and its check at ``margin`` (m), on a model and data of its own (one
    thread uses one ``BodyCheck``).

    ``check(command, position, velocity)`` puts the pose (from the command and the measured positions and
    velocities) and finds every checked pair closer than the margin (``contacts``); ``closing`` keeps those the
    command brings nearer than the measured pose has them.
    ``arm_joints[group]`` are the joints that carry an arm's bodies: what the gate holds when an arm is refused.
    """

    def __init__(self, robot: Robot, margin: float, stopping_time: float = 0.0,
                 model: mujoco.MjModel | None = None) -> None:
        self.robot = robot
        self.margin = float(margin)
        self.stopping_time = float(stopping_time)
        self._still = np.zeros(robot.n)
        self.model = model if model is not None else load_model(robot)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.joint_ids = np.array([m.joint(name).id for name in robot.names], dtype=np.intp)
        qadr = np.ascontiguousarray(m.jnt_qposadr[self.joint_ids], dtype=np.intp)
        self.geom_group = {g: GROUPS.get(int(m.geom_contype[g]), "") for g in range(m.ngeom)}
        self.pairs = np.array(_collided_pairs(m), dtype=np.intc).reshape(-1, 2)
        self.body_names = [m.body(int(m.geom_bodyid[g])).name for g in range(m.ngeom)]
        # Per geom, the robot joints that move it (bit j for joint j); per joint, the class of the bodies it carries.
        joint_of_body = {int(m.jnt_bodyid[jid]): j for j, jid in enumerate(self.joint_ids)}
        self.chain = np.zeros(m.ngeom, dtype=np.uint64)
        for g in range(m.ngeom):
            body = int(m.geom_bodyid[g])
            while body > 0:
                if body in joint_of_body:
                    self.chain[g] |= np.uint64(1 << joint_of_body[body])
                body = int(m.body_parentid[body])
        # Per joint, the joints that carry it (itself and every joint between it and the torso).
        self.carriers = np.zeros(robot.n, dtype=np.uint64)
        for j, jid in enumerate(self.joint_ids):
            body = int(m.jnt_bodyid[jid])
            while body > 0:
                if body in joint_of_body:
                    self.carriers[j] |= np.uint64(1 << joint_of_body[body])
                body = int(m.body_parentid[body])
        self.arm_joints: dict[str, npt.NDArray[np.bool_]] = {}
        for group in ("left arm", "right arm"):
            carried = np.zeros(robot.n, dtype=bool)
            for g in range(m.ngeom):
                if self.geom_group[g] == group:
                    carried |= [(int(self.chain[g]) >> j) & 1 == 1 for j in range(robot.n)]
            self.arm_joints[group] = carried
        self._chains = np.ascontiguousarray(np.bitwise_or(self.chain[self.pairs[:, 0]], self.chain[self.pairs[:, 1]]),
                                            dtype=np.uint64)
        self.live = np.ones(len(self.pairs), dtype=np.uint8)  # the pairs no unknown joint moves (the kernel's)
        self._pair_arms = [tuple(self.geom_group[int(g)] for g in pair if self.geom_group[int(g)] in self.arm_joints)
                           for pair in self.pairs]
        self.kernel = BodyKernel(mujoco_library(), m, self.data, qadr, np.ascontiguousarray(robot.lower),
                                 np.ascontiguousarray(robot.upper), self.pairs, self._chains, self.live, self.margin)
        self._identity = (np.ones(robot.n), np.zeros(robot.n), np.ones(robot.n, dtype=np.uint8))
        self.kernel.frame(*self._identity)

    def frame(self, frame: Frame | None) -> None:
        """Move the poses into the model's frame by ``frame`` (its arrays are read at every check; a calibration run
        changes them as it learns). None: the identity, every joint known (a calibrated robot's joint frame)."""
        if frame is None:
            self.kernel.frame(*self._identity)
        else:
            self.kernel.frame(frame.scale, frame.shift, frame.known)

    def _pose(self, command: npt.NDArray[np.float64], position: npt.NDArray[np.float64],
              velocity: npt.NDArray[np.float64] | None, targets: bool) -> None:
        self.kernel.pose(command, position, self._still if velocity is None else velocity, self.stopping_time, targets)

    def check(self, command: npt.NDArray[np.float64], position: npt.NDArray[np.float64],
              velocity: npt.NDArray[np.float64] | None = None) -> int:
        """How many checked pairs the pose of ``command`` brings closer than the margin (the hot path: one call)."""
        return int(self.kernel.check(command, position, self._still if velocity is None else velocity,
                                     self.stopping_time))

    def contacts(self) -> list[Contact]:
        """The pairs the last ``check`` found, nearest first."""
        found = sorted(zip(self.kernel.found.tolist(), self.kernel.found_distance.tolist(), strict=True),
                       key=lambda item: item[1])
        return [self.contact(pair, distance) for pair, distance in found]

    def arms_of(self, pair: int) -> tuple[str, ...]:
        """The arms (``arm_joints`` keys) the pair's bodies belong to."""
        return self._pair_arms[pair]

    def contact(self, pair: int, distance: float) -> Contact:
        """Pair ``pair`` at ``distance``, named."""
        a, b = (int(g) for g in self.pairs[pair])
        return Contact(self.body_names[a], self.body_names[b], self.geom_group[a], self.geom_group[b], distance)

    def closing(self, command: npt.NDArray[np.float64], position: npt.NDArray[np.float64],
                velocity: npt.NDArray[np.float64] | None = None) -> list[Contact]:
        """The pairs the pose of ``command`` brings closer than the margin and nearer than the measured pose has
        them, nearest first: what the command would drive into. A command that keeps or widens a distance already
        under the margin (an arm moving away from the torso it rests against) closes nothing."""
        if not self.check(command, position, velocity):
            return []
        return [self.contact(pair, distance) for pair, distance in self.closing_found(command, position)]

    def closing_found(self, command: npt.NDArray[np.float64],
                      position: npt.NDArray[np.float64]) -> list[tuple[int, float]]:
        """Of the pairs the last ``check`` of ``command`` found, those nearer than the measured pose has them:
        (pair, distance), nearest first."""
        found = list(zip(self.kernel.found.tolist(), self.kernel.found_distance.tolist(), strict=True))
        self._pose(command, position, None, False)
        closing = [(pair, distance) for pair, distance in found
                   if distance < self.kernel.distance_of(pair, FAR_M) - CLOSING_TOLERANCE_M]
        return sorted(closing, key=lambda item: item[1])

    def clearance(self, command: npt.NDArray[np.float64], position: npt.NDArray[np.float64]) -> Contact | None:
        """The nearest checked pair at the pose of ``command``, whatever its distance (None: nothing is checked)."""
        self._pose(command, position, None, True)
        best: tuple[int, float] | None = None
        for pair in np.flatnonzero(self.live):
            distance = float(self.kernel.distance_of(int(pair), FAR_M))
            if best is None or distance < best[1]:
                best = (int(pair), distance)
        return None if best is None else self.contact(*best)

    def sweep(self, measured: npt.NDArray[np.float64], joint: int, angles: npt.NDArray[np.float64],
              frame: Frame) -> tuple[Contact | None, float] | None:
        """``joint`` at each of ``angles`` (model frame), every other joint where it is measured (moved into the
        model's frame by ``frame``): the first angle at which a pair its motion moves comes closer than the margin,
        and that pair, or (None, nan). None: its place cannot be known (a joint that carries it is unknown)."""
        scale, shift, known = frame.scale.copy(), frame.shift.copy(), frame.known.copy()
        known[joint] = 1
        others = int(self.carriers[joint]) & ~(1 << joint)
        if any(not (known[j] and np.isfinite(measured[j])) for j in range(self.robot.n) if others >> j & 1):
            return None
        scale[joint] = 0.0  # the joint at ``shift``, wherever it is measured
        no_targets = np.zeros((5, self.robot.n))
        moved = np.uint64(1 << joint)
        self.kernel.frame(scale, shift, known)
        try:
            for angle in angles:
                shift[joint] = angle
                if not self.check(no_targets, measured):
                    continue
                for pair, distance in zip(self.kernel.found.tolist(), self.kernel.found_distance.tolist(), strict=True):
                    if self._chains[pair] & moved:
                        return self.contact(pair, distance), float(angle)
            return None, math.nan
        finally:
            self.kernel.frame(*self._identity)


def _collided_pairs(m: mujoco.MjModel) -> list[tuple[int, int]]:
    """The geom pairs MuJoCo collides in ``m``: compatible contype/conaffinity, not on one body or two welded
    together, not a body and its parent (unless the parent is the world), not an excluded body pair."""
    excluded = {int(s) for s in m.exclude_signature}
    pairs = []
    for a in range(m.ngeom):
        for b in range(a + 1, m.ngeom):
            if not (m.geom_contype[a] & m.geom_conaffinity[b] or m.geom_contype[b] & m.geom_conaffinity[a]):
                continue
            ba, bb = int(m.geom_bodyid[a]), int(m.geom_bodyid[b])
            wa, wb = int(m.body_weldid[ba]), int(m.body_weldid[bb])
            if wa == wb:
                continue
            parent_a, parent_b = int(m.body_weldid[m.body_parentid[wa]]), int(m.body_weldid[m.body_parentid[wb]])
            if (parent_a == wb and wb != 0) or (parent_b == wa and wa != 0):
                continue  # MuJoCo's parent filter
            low, high = min(ba, bb), max(ba, bb)
            if (low << 16) + high in excluded:
                continue
            pairs.append((a, b))
    return pairs
