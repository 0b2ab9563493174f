"""``prime_calibration.yaml``: per joint ``direction`` (wiring, +1/-1) and ``homing_offset`` (rad).

``q_joint = direction * (q_raw - homing_offset)`` and ``q_raw = direction * q_joint + homing_offset``;
velocity and effort use ``direction`` only (DESIGN §2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

from humanoid_prime.config.hardware import HardwareConfig
from humanoid_prime.errors import ConfigError
from humanoid_prime.files import atomic_write_yaml, bundled, check_keys, config_path, load_yaml

if TYPE_CHECKING:  # numpy is imported where the arrays are made: reading a calibration (`prime info`) needs none
    import numpy as np
    import numpy.typing as npt

CALIBRATION_FILE = "prime_calibration.yaml"
HEADER = (
    "# Per-robot calibration: joint = direction * (raw - homing_offset).\n"
    "# direction is a wiring fact (+1/-1); homing_offset (rad) is measured per physical robot\n"
    "# with `prime calibrate`. bus/address are for people; the hardware file is authoritative.\n"
)
# The header line of a file a run on a virtual robot wrote: such a file may be replaced by another virtual run.
VIRTUAL_MARK = "# calibrated on a virtual robot (--emulate or --sim), not on a physical one\n"


def virtual_may_replace(path: Path, hardware: HardwareConfig) -> bool:
    """Whether a run on a virtual robot may write its result over ``path`` when the user named no output: only
    when there is nothing there, a virtual run wrote it, or it holds no measurement (every joint identity, as
    `prime config init` leaves it). A physical robot's offsets are never replaced by a simulation's."""
    if not path.is_file():
        return True
    if VIRTUAL_MARK in path.read_text(errors="replace"):
        return True
    held = load_calibration(hardware, path)
    return all(c == JointCalibration() for c in held.joints.values())


def is_virtual(path: Path) -> bool:
    """Whether a virtual run wrote the calibration file at ``path`` (a flip keeps that mark)."""
    return path.is_file() and VIRTUAL_MARK in path.read_text(errors="replace")


@dataclass(frozen=True)
class JointCalibration:
    direction: int = 1
    homing_offset: float = 0.0


@dataclass(frozen=True)
class Calibration:
    """Calibration of every joint, keyed by name, in canonical order."""

    joints: dict[str, JointCalibration]
    path: Path | None = field(default=None, compare=False)

    def direction_array(self, names: tuple[str, ...]) -> npt.NDArray[np.float64]:
        import numpy as np

        return np.array([self.joints[n].direction for n in names], dtype=np.float64)

    def offset_array(self, names: tuple[str, ...]) -> npt.NDArray[np.float64]:
        import numpy as np

        return np.array([self.joints[n].homing_offset for n in names], dtype=np.float64)

    @property
    def is_identity(self) -> bool:
        """Every homing offset 0: the template, not a robot's calibration (no calibrated robot reads 0 on all)."""
        return all(c.homing_offset == 0.0 for c in self.joints.values())

    def with_joint(self, name: str, value: JointCalibration) -> Calibration:
        joints = dict(self.joints)
        joints[name] = value
        return replace(self, joints=joints)


def identity_calibration(hardware: HardwareConfig, directions: dict[str, int] | None = None) -> Calibration:
    """Offset 0 on every joint; directions from ``directions`` (a prior file's) or +1."""
    directions = directions or {}
    return Calibration({n: JointCalibration(directions.get(n, 1), 0.0) for n in hardware.all_joints})


def load_calibration(hardware: HardwareConfig, path: str | Path | None = None) -> Calibration:
    """Load a calibration file for every joint of ``hardware`` and check it names exactly those joints."""
    path = config_path(path) if path is not None else bundled(CALIBRATION_FILE)
    data = load_yaml(path)
    check_keys(path, "", data, ("joints",))
    joints = data.get("joints")
    if not isinstance(joints, dict):
        raise ConfigError(path, "joints", "missing or not a mapping",
                          "one entry per joint with direction and homing_offset")
    for name in joints:
        if name not in hardware.all_joints:
            raise ConfigError(path, f"joints.{name}", f"{name!r} matches no joint of {hardware.path.name}",
                              "fix the name or remove the entry")
    result: dict[str, JointCalibration] = {}
    for name in hardware.all_joints:
        key = f"joints.{name}"
        entry = joints.get(name)
        if not isinstance(entry, dict):
            raise ConfigError(path, key, "missing", "add it with direction: 1 and homing_offset: 0.0")
        check_keys(path, key, entry, ("direction", "homing_offset", "bus", "address"))
        direction = entry.get("direction")
        if isinstance(direction, bool) or direction not in (1, -1):
            raise ConfigError(path, f"{key}.direction", f"must be 1 or -1, got {direction!r}")
        offset = entry.get("homing_offset")
        if isinstance(offset, bool) or not isinstance(offset, (int, float)) or not math.isfinite(offset):
            raise ConfigError(path, f"{key}.homing_offset", f"must be a finite number of radians, got {offset!r}")
        for note, value in zip(("bus", "address"), _where(hardware, name), strict=True):
            given = entry.get(note)
            if given is not None and given != value:
                raise ConfigError(path, f"{key}.{note}", f"{given!r}, but {hardware.path} puts {name} on "
                                  f"{value!r}", "the file was written for another wiring: check this joint's "
                                  "direction and offset, then correct the line or delete it")
        result[name] = JointCalibration(int(direction), float(offset))
    return Calibration(result, path=path)


class JointEntry(TypedDict):
    """One joint of a calibration file."""

    direction: int
    homing_offset: float
    bus: str
    address: str


def _where(hardware: HardwareConfig, name: str) -> tuple[str, str]:
    """The bus and address a calibration file writes beside a joint, for people (and checked on load)."""
    if name in hardware.erob_slaves:
        return "ethercat", f"ring {hardware.erob_slaves[name]}"
    return "can", f"id {hardware.mit_joints[name]}"


def calibration_document(calibration: Calibration, hardware: HardwareConfig) -> dict[str, dict[str, JointEntry]]:
    """The YAML document for ``calibration``, with the human-readable bus and address of each joint."""
    joints: dict[str, JointEntry] = {}
    for name in hardware.all_joints:
        cal = calibration.joints[name]
        bus, address = _where(hardware, name)
        joints[name] = {
            "direction": int(cal.direction),
            "homing_offset": round(float(cal.homing_offset), 6) + 0.0,  # never "-0.0"
            "bus": bus,
            "address": address,
        }
    return {"joints": joints}


def save_calibration(path: str | Path, calibration: Calibration, hardware: HardwareConfig,
                     comment: str = "") -> None:
    """Write the calibration atomically: the old file stays intact until the new one is complete. ``comment``
    (YAML comment lines) follows the standard header."""
    atomic_write_yaml(path, calibration_document(calibration, hardware), header=HEADER + comment)
