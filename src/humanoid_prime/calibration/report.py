"""What a hands-free calibration found (``calibration.auto``), as the report and the summary give it: per joint its
outcome (the calibration written or why not, the stops, the contact effort against the cap and the speed it met
them at, its robot time and what it went to, the drive's own torque limit) and, when measured, the impedance it
realised against its stops; for the run, the calibration file's content, the mirror check of the two arms, its
robot time and wall time and where the robot time went."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NotRequired, TypedDict

import numpy as np

from humanoid_prime.calibration.approach import Trace
from humanoid_prime.calibration.math import mirror_check
from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.config.robot import Robot
from humanoid_prime.drivers.erob.gains import gains_to_registers, registers_to_gains
from humanoid_prime.drivers.sito.protocol import sito_model


class StiffnessReport(TypedDict):
    """``Stiffness.as_dict``: asked, realised and their ratio; an eRob's torque efficiency, a Sito's divisors."""

    kp_asked: float
    kp_realised: float
    kp_ratio: float
    kd_asked: float
    kd_realised: float
    kd_ratio: float
    points: int
    torque_efficiency: NotRequired[float]
    kp_divisor: NotRequired[float]
    kd_divisor: NotRequired[float]


@dataclass
class Stiffness:
    """The impedance a joint realised against its stops: torque over position error, and over speed error."""

    family: str
    kp_asked: float  # what the host asked for (eRob: the registers' nominal stiffness)
    kd_asked: float
    kp: float
    kd: float
    points: int

    @property
    def kp_ratio(self) -> float:
        return self.kp / self.kp_asked

    @property
    def kd_ratio(self) -> float:
        return self.kd / self.kd_asked

    def as_dict(self) -> StiffnessReport:
        out: StiffnessReport = {"kp_asked": self.kp_asked, "kp_realised": self.kp, "kp_ratio": self.kp_ratio,
                                "kd_asked": self.kd_asked, "kd_realised": self.kd, "kd_ratio": self.kd_ratio,
                                "points": self.points}
        if self.family == "erob":
            out["torque_efficiency"] = self.kp_ratio  # realised/nominal: the hardware file's correction
        else:
            model = sito_model("TA40-50")
            out["kp_divisor"] = model.kp_divisor * self.kp_ratio  # what the firmware divides by, measured
            out["kd_divisor"] = model.kd_divisor * self.kd_ratio
        return out


@dataclass
class JointOutcome:
    joint: str
    status: str  # done | skipped | failed | aborted | direction_unknown | not_reached
    message: str = ""
    prior: JointCalibration = field(default_factory=JointCalibration)
    calibration: JointCalibration | None = None  # what is written (None: the prior is kept)
    stops: tuple[float, float] | None = None  # identity frame (prior direction, offset 0), lower reading first
    first_side: int = 0
    direction_source: str = ""
    stiffness: Stiffness | None = None
    peak_contact_nm: float = 0.0
    cap_nm: float = 0.0
    impact_rad_s: float = 0.0  # the fastest it met a stop at
    seconds: float = 0.0  # robot time the joint took
    times: dict[str, float] = field(default_factory=dict)  # robot time by what it went to (approach.KINDS)
    drive_torque_limit: str = ""  # what became of the drive's own torque limit
    warnings: list[str] = field(default_factory=list)  # what went against the plan (a stop met too fast)

    @property
    def done(self) -> bool:
        return self.status == "done"

    @property
    def flipped(self) -> bool:
        return self.calibration is not None and self.calibration.direction != self.prior.direction

    def as_dict(self) -> dict[str, object]:
        cal = self.calibration
        return {"status": self.status, "message": self.message,
                "direction": cal.direction if cal else self.prior.direction,
                "homing_offset": cal.homing_offset if cal else self.prior.homing_offset,
                "prior_direction": self.prior.direction, "prior_offset": self.prior.homing_offset,
                "flipped": self.flipped, "direction_source": self.direction_source,
                "stops": list(self.stops) if self.stops else None, "cap_nm": self.cap_nm,
                "peak_contact_nm": self.peak_contact_nm, "impact_rad_s": self.impact_rad_s,
                "seconds": self.seconds, "times": dict(self.times), "drive_torque_limit": self.drive_torque_limit,
                "warnings": list(self.warnings),
                "stiffness": self.stiffness.as_dict() if self.stiffness else None}


@dataclass
class AutoResult:
    calibration: Calibration  # every joint: the new one where done, the prior elsewhere
    outcomes: dict[str, JointOutcome]
    traces: dict[str, Trace]
    asked: tuple[str, ...]
    aborted: str | None
    robot: Robot
    robot_seconds: float = 0.0  # the run's robot time
    wall_seconds: float = 0.0
    timeline: list[tuple[str, float, float]] = field(default_factory=list)  # (what, from, to): robot time

    @property
    def complete(self) -> bool:
        """Every joint asked for was calibrated and nothing stopped the run."""
        return self.aborted is None and all(self.outcomes[j].done for j in self.asked)

    def time_by_kind(self) -> dict[str, float]:
        """Every joint's robot time added up by what it went to (joints that moved together both count)."""
        total: dict[str, float] = {}
        for joint in self.asked:
            for kind, seconds in self.outcomes[joint].times.items():
                total[kind] = total.get(kind, 0.0) + seconds
        return total

    def as_dict(self) -> dict[str, object]:
        mirror = mirror_check(self.calibration, self.robot)
        return {"complete": self.complete, "aborted": self.aborted, "robot_seconds": self.robot_seconds,
                "wall_seconds": self.wall_seconds,
                "timeline": [{"what": what, "from_s": start, "to_s": end} for what, start, end in self.timeline],
                "joint_seconds_by_kind": self.time_by_kind(),
                "joints": {j: self.outcomes[j].as_dict() for j in self.asked},
                "mirror": [{"left": m.left, "right": m.right, "left_offset": m.left_offset,
                            "right_offset": m.right_offset, "relation": m.relation, "residual": m.residual,
                            "ok": m.ok} for m in mirror]}


def fit_stiffness(robot: Robot, joint: str, on_ring: bool, gains: tuple[float, float],
                  points: list[list[tuple[float, float, float]]]) -> Stiffness | None:
    """The stiffness and damping ``joint`` realised: the effort pressed into each stop (``points``: per stop, per
    tick, lag, speed command and effort) against the lag and the speed, ``effort = kp * lag + kd * speed + (one
    constant per stop)``, by least squares; beside what was asked (``gains``, an eRob ``on_ring``: what its
    registers give nominally)."""
    pressed = [stop for stop in points if len(stop) >= 5]
    if not pressed:
        return None
    rows, efforts = [], []
    for k, stop in enumerate(pressed):
        for lag, speed, effort in stop:
            rows.append([lag, speed, *(1.0 if m == k else 0.0 for m in range(len(pressed)))])
            efforts.append(effort)
    (kp, kd, *_), *_ = np.linalg.lstsq(np.array(rows), np.array(efforts), rcond=None)
    hw = robot.hardware
    if on_ring:
        registers = gains_to_registers(*gains, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint],
                                       efficiency=hw.erob_torque_efficiency[joint])
        kp_asked, kd_asked = registers_to_gains(registers, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint])
        family = "erob"
    else:
        kp_asked, kd_asked = gains
        family = "erob" if joint in hw.erob_slaves else "sito"
    return Stiffness(family, kp_asked, kd_asked, float(kp), float(kd), len(efforts))
