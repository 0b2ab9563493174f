"""Calibration math: offsets from sweeps, direction flips, and the left/right mirror check (DESIGN §5).

``q_joint = direction * (q_raw - homing_offset)``. Sweeps are sampled in the identity frame (the prior
direction applied, offset 0), so a joint swept stop to stop reads ``[lower, upper] + direction * offset``.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from enum import StrEnum

from humanoid_prime.config.calibration import Calibration, JointCalibration
from humanoid_prime.config.robot import Robot

MIN_SWEEP_RAD = 0.5  # a shorter sweep did not reach both stops; keep the prior offset (DESIGN §5)
FULL_SWEEP_FRACTION = 0.95  # a stop-to-stop sweep spans the described range; much less means a stop was missed
FLIP_OFFSET_RAD = math.pi  # an offset beyond half a turn means the direction is probably wrong (DESIGN §5)
MIRROR_TOLERANCE_RAD = 0.1  # assembly tolerance between the arms' offsets; a cross-check, not a hardware fact


@dataclass(frozen=True)
class SweepStats:
    """Smallest and largest identity-frame position seen while a joint was swept."""

    min: float
    max: float

    @property
    def span(self) -> float:
        return self.max - self.min


class Status(StrEnum):
    CALIBRATED = "calibrated"
    SKIPPED = "skipped"  # sweep under MIN_SWEEP_RAD: prior kept
    PROBABLE_FLIP = "probable_flip"  # offset written but flagged: flip the direction or re-sweep
    CARRIED = "carried"  # no samples: prior kept


@dataclass(frozen=True)
class JointReport:
    joint: str
    status: Status
    direction: int
    offset: float  # the offset in the new calibration
    prior_offset: float
    sweep: SweepStats | None
    message: str


def offset_from_sweep(sample_min: float, sample_max: float, lower: float, upper: float, direction: int) -> float:
    """Homing offset that maps an identity-frame sweep onto the described limits, averaged over both stops."""
    return 0.5 * ((sample_min - lower) + (sample_max - upper)) * direction


def _misses_limits(sweep: SweepStats, lower: float, upper: float) -> bool:
    return sweep.max < lower or sweep.min > upper


def calibrate_from_sweeps(sweeps: Mapping[str, SweepStats | tuple[float, float]], prior: Calibration,
                          robot: Robot, *, max_first: Collection[str] = ()) -> tuple[Calibration, list[JointReport]]:
    """New calibration of every joint of ``robot`` from the sweeps, carrying ``prior`` where there is none.

    Directions stay as in ``prior`` (the sweeps were sampled with them). A joint whose offset exceeds half
    a turn, or whose sweep misses the described range entirely, gets the computed offset but is reported
    as a probable direction flip, so ``flip_direction`` can fix it without a re-sweep. ``max_first`` names
    joints whose trace reached its maximum before its minimum although the operator swept to the lower
    stop first: the same flag. (A sweep alone cannot show a flip on a symmetric joint: its range maps onto
    the limits either way; the order of the stops can.)
    """
    unknown = sorted(set(sweeps) - set(robot.names))
    if unknown:
        raise ValueError(f"sweeps name joints Prime does not have: {', '.join(unknown)}")
    joints: dict[str, JointCalibration] = {}
    reports: list[JointReport] = []
    for spec in robot.joints:
        before = prior.joints[spec.name]
        raw = sweeps.get(spec.name)
        sweep = raw if isinstance(raw, SweepStats) or raw is None else SweepStats(*raw)
        if sweep is None or not (math.isfinite(sweep.min) and math.isfinite(sweep.max)) or sweep.span < 0:
            status, offset, sweep = Status.CARRIED, before.homing_offset, None
            message = "no samples; prior offset kept"
        elif sweep.span < MIN_SWEEP_RAD:
            status, offset = Status.SKIPPED, before.homing_offset
            message = f"sweep {sweep.span:.3f} rad is under {MIN_SWEEP_RAD} rad; prior offset kept"
        else:
            offset = offset_from_sweep(sweep.min, sweep.max, spec.lower, spec.upper, before.direction)
            if abs(offset) > FLIP_OFFSET_RAD:
                status = Status.PROBABLE_FLIP
                message = (f"|offset| {abs(offset):.3f} rad is over pi: probably a direction flip; "
                           f"run `prime calibration flip {spec.name}` or re-sweep with the other direction")
            elif _misses_limits(sweep, spec.lower, spec.upper):
                status = Status.PROBABLE_FLIP
                message = (f"sweep [{sweep.min:.3f}, {sweep.max:.3f}] misses the limits "
                           f"[{spec.lower}, {spec.upper}]: probably a direction flip; "
                           f"run `prime calibration flip {spec.name}` or re-sweep with the other direction")
            elif spec.name in max_first:
                status = Status.PROBABLE_FLIP
                message = ("swept to the lower stop first, but the reading rose to its maximum first: probably "
                           f"a direction flip; run `prime calibration flip {spec.name}`")
            else:
                status = Status.CALIBRATED
                coverage = sweep.span / (spec.upper - spec.lower)
                message = f"sweep {sweep.span:.3f} rad, {coverage:.0%} of the described range"
                if coverage < FULL_SWEEP_FRACTION:
                    message += ": short of stop to stop, were both stops reached? (the offset assumes they were)"
        joints[spec.name] = JointCalibration(before.direction, offset)
        reports.append(JointReport(spec.name, status, before.direction, offset, before.homing_offset, sweep, message))
    return Calibration(joints), reports


def flip_direction(cal: JointCalibration, lower: float, upper: float) -> JointCalibration:
    """The calibration with the direction negated and the offset a re-sweep would give, without re-sweeping.

    ``offset + direction * (lower + upper)``: for the usual +1 -> -1 flip that is ``offset + lower + upper``;
    a symmetric joint keeps its offset, and flipping twice restores the original.
    """
    return JointCalibration(-cal.direction, cal.homing_offset + cal.direction * (lower + upper))


def probable_flips(calibration: Calibration) -> list[str]:
    """Joints whose offset exceeds half a turn (probably a wrong direction)."""
    return [name for name, cal in calibration.joints.items() if abs(cal.homing_offset) > FLIP_OFFSET_RAD]


@dataclass(frozen=True)
class MirrorRow:
    left: str
    right: str
    left_offset: float
    right_offset: float
    relation: str  # "opposite" for mirrored limits (offsets sign-flipped), else "equal"
    residual: float  # left + right when opposite, left - right when equal

    @property
    def ok(self) -> bool:
        return abs(self.residual) <= MIRROR_TOLERANCE_RAD


def mirror_check(calibration: Calibration, robot: Robot) -> list[MirrorRow]:
    """Compare each left joint's offset with its right twin's.

    A joint whose left limits are the right ones negated and swapped (and differ from them, like
    shoulder_roll) is expected to have a sign-flipped offset; every other pair an equal one.
    """
    by_name = {j.name: j for j in robot.joints}
    rows = []
    for left in robot.joints:
        if not left.name.startswith("left_"):
            continue
        right = by_name.get("right_" + left.name.removeprefix("left_"))
        if right is None:
            continue
        mirrored = ((left.lower, left.upper) != (right.lower, right.upper)
                    and math.isclose(left.lower, -right.upper) and math.isclose(left.upper, -right.lower))
        lo, ro = calibration.joints[left.name].homing_offset, calibration.joints[right.name].homing_offset
        relation, residual = ("opposite", lo + ro) if mirrored else ("equal", lo - ro)
        rows.append(MirrorRow(left.name, right.name, lo, ro, relation, residual))
    return rows
