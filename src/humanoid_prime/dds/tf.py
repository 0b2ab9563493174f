"""The robot's frames for ``/tf`` and ``/tf_static``, from the robot description, as robot_state_publisher
gives them: one transform per joint, parent link to child link; the fixed joints once (``/tf_static``), the
actuated ones from the measured positions (``/tf``).

A joint's transform is its ``<origin>`` (xyz, then roll-pitch-yaw) followed by the rotation about its
``<axis>`` by the joint's position (a prismatic joint: the translation along it). The per-tick part is a few
vector operations on all actuated joints at once.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from humanoid_prime.errors import PrimeError

Array = npt.NDArray[np.float64]


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> Array:
    """(x, y, z, w) of the URDF rotation: roll about x, then pitch about y, then yaw about z (fixed axes)."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.array([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
                     cr * cp * cy + sr * sp * sy])


def quaternion_multiply(a: Array, b: Array) -> Array:
    """Hamilton product of (x, y, z, w) quaternions, row by row (a's rotation, then b's, in a's frame)."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def rotate(q: Array, v: Array) -> Array:
    """``v`` rotated by the unit quaternion ``q`` (x, y, z, w)."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


@dataclass(frozen=True)
class Frames:
    """The description's joints: fixed ones as ready transforms, actuated ones in the canonical order."""

    root: str
    static_parents: tuple[str, ...]
    static_children: tuple[str, ...]
    static_translations: Array  # (n_fixed, 3)
    static_rotations: Array  # (n_fixed, 4) x, y, z, w
    parents: tuple[str, ...]  # actuated joints, canonical order
    children: tuple[str, ...]
    origins: Array  # (n, 3)
    origin_rotations: Array  # (n, 4)
    axes: Array  # (n, 3), unit
    prismatic: Array  # (n,) bool

    # The common case (Prime's description): revolute joints whose origins do not rotate; a few vector operations
    # then give every transform.
    _turned: bool = field(init=False)
    _slides: bool = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_turned", not np.allclose(self.origin_rotations, [0.0, 0.0, 0.0, 1.0]))
        object.__setattr__(self, "_slides", bool(self.prismatic.any()))

    def transforms(self, positions: Array) -> tuple[Array, Array]:
        """Translations (n, 3) and rotations (n, 4) of each actuated joint's child in its parent, at
        ``positions`` (canonical order; NaN, not measured, counts as 0)."""
        q = np.nan_to_num(positions, nan=0.0)
        half = (np.where(self.prismatic, 0.0, q) if self._slides else q) * 0.5
        rotations = np.empty((len(q), 4))
        np.multiply(self.axes, np.sin(half)[:, None], out=rotations[:, :3])
        np.cos(half, out=rotations[:, 3])
        if self._turned:
            rotations = quaternion_multiply(self.origin_rotations, rotations)
        if not self._slides:
            return self.origins, rotations
        slide = np.where(self.prismatic, q, 0.0)[:, None] * self.axes
        return self.origins + rotate(self.origin_rotations, slide), rotations

    def link_pose(self, link: str, positions: Array) -> tuple[Array, Array]:
        """The pose of ``link`` in the root link at ``positions``: translation (3,) and rotation (4,)."""
        translations, rotations = self.transforms(positions)
        parent_of = {c: (p, self.static_translations[i], self.static_rotations[i])
                     for i, (p, c) in enumerate(zip(self.static_parents, self.static_children, strict=True))}
        parent_of.update({c: (p, translations[i], rotations[i])
                          for i, (p, c) in enumerate(zip(self.parents, self.children, strict=True))})
        translation, rotation = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        while link != self.root:
            if link not in parent_of:
                raise PrimeError(f"link {link!r} is not in the robot description")
            link, t, r = parent_of[link]
            translation = t + rotate(r, translation)
            rotation = quaternion_multiply(r, rotation)
        return translation, rotation


def _floats(text: str | None, default: str) -> Array:
    return np.array([float(v) for v in (text or default).split()])


def frames_from_urdf(urdf: str, joint_names: tuple[str, ...]) -> Frames:
    """The frames of ``urdf``; ``joint_names`` (the canonical order) are its actuated joints."""
    root = ET.fromstring(urdf)
    fixed: list[tuple[str, str, Array, Array]] = []
    moving: dict[str, tuple[str, str, Array, Array, Array, bool]] = {}
    children = set()
    for joint in root.findall("joint"):
        kind = joint.get("type")
        parent = joint.find("parent").get("link", "")  # type: ignore[union-attr]  # URDF: every joint has both
        child = joint.find("child").get("link", "")  # type: ignore[union-attr]
        children.add(child)
        origin = joint.find("origin")
        xyz = _floats(origin.get("xyz") if origin is not None else None, "0 0 0")
        rotation = quaternion_from_rpy(*_floats(origin.get("rpy") if origin is not None else None, "0 0 0"))
        if kind == "fixed":
            fixed.append((parent, child, xyz, rotation))
        elif kind in ("revolute", "continuous", "prismatic"):
            axis_element = joint.find("axis")
            axis = _floats(axis_element.get("xyz") if axis_element is not None else None, "1 0 0")
            moving[joint.get("name", "")] = (parent, child, xyz, rotation, axis / np.linalg.norm(axis),
                                             kind == "prismatic")
        else:
            raise PrimeError(f"joint {joint.get('name')!r} of type {kind!r}: /tf covers fixed, revolute, "
                             "continuous and prismatic joints")
    missing = [name for name in joint_names if name not in moving]
    if missing:
        raise PrimeError(f"the robot description has no actuated joint {', '.join(missing)}")
    roots = [link.get("name", "") for link in root.findall("link") if link.get("name") not in children]
    rows = [moving[name] for name in joint_names]
    return Frames(
        root=roots[0] if roots else "",
        static_parents=tuple(p for p, _, _, _ in fixed), static_children=tuple(c for _, c, _, _ in fixed),
        static_translations=np.array([t for _, _, t, _ in fixed]).reshape(-1, 3),
        static_rotations=np.array([r for _, _, _, r in fixed]).reshape(-1, 4),
        parents=tuple(r[0] for r in rows), children=tuple(r[1] for r in rows),
        origins=np.array([r[2] for r in rows]), origin_rotations=np.array([r[3] for r in rows]),
        axes=np.array([r[4] for r in rows]), prismatic=np.array([r[5] for r in rows]))
