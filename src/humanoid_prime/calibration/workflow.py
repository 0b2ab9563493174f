"""The per-robot calibration run (DESIGN §5) on top of a broadcaster-only bringup.

``prime calibrate`` brings up the chosen buses with identity calibration (the prior file's directions,
offset 0) and only the joint-state broadcaster, tracks every joint's min/max while the joints are swept
to both mechanical stops, and on stop computes the offsets and writes a complete 14-joint file
atomically, carrying the prior through for joints it did not see. ``--verify`` brings the robot up with
a finished calibration and checks that a joint at a stop reads that stop's description limit.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from humanoid_prime.calibration.math import JointReport, MirrorRow, Status, calibrate_from_sweeps, mirror_check
from humanoid_prime.calibration.tracker import SweepRow, SweepTracker
from humanoid_prime.config.calibration import Calibration, JointCalibration, save_calibration
from humanoid_prime.config.description import BACKEND_BLOCKS
from humanoid_prime.config.robot import Robot
from humanoid_prime.errors import PrimeError

VERIFY_TOLERANCE_RAD = 0.002


def tracked_joints(robot: Robot, backends: str) -> tuple[str, ...]:
    """The joints a run on ``backends`` sees: the description's EtherCAT block, its CAN block, or both."""
    joints = {j for name in BACKEND_BLOCKS[backends] for j in robot.description.block(name).joints}
    return tuple(j for j in robot.names if j in joints)


def identity_from(prior: Calibration) -> Calibration:
    """Directions of ``prior`` (a wiring fact), offsets 0: the frame the sweep is sampled in."""
    return Calibration({j: JointCalibration(c.direction, 0.0) for j, c in prior.joints.items()})


def check_joint_names(robot: Robot, joints: Sequence[str], allowed: Sequence[str], what: str) -> None:
    for joint in joints:
        if joint not in robot.names:
            raise PrimeError(f"{what}: unknown joint {joint!r}; known joints: {', '.join(robot.names)}")
        if joint not in allowed:
            raise PrimeError(f"{what}: {joint} is not on the buses of this run ({', '.join(allowed)})")


@dataclass(frozen=True)
class CalibrationResult:
    calibration: Calibration
    reports: list[JointReport]
    mirror: list[MirrorRow]
    rows: list[SweepRow]
    robot: Robot

    @property
    def swept(self) -> bool:
        """Some joint was swept far enough to compute its offset (calibrated, or flagged as a probable flip)."""
        return any(r.status in (Status.CALIBRATED, Status.PROBABLE_FLIP) for r in self.reports)

    def as_dict(self) -> dict[str, object]:
        return {
            "joints": {r.joint: {"status": str(r.status), "direction": r.direction, "homing_offset": r.offset,
                                 "prior_offset": r.prior_offset, "message": r.message,
                                 "sweep": None if r.sweep is None else [r.sweep.min, r.sweep.max]}
                       for r in self.reports},
            "mirror": [{"left": m.left, "right": m.right, "left_offset": m.left_offset,
                        "right_offset": m.right_offset, "relation": m.relation, "residual": m.residual, "ok": m.ok}
                       for m in self.mirror],
        }


def compute(tracker: SweepTracker, prior: Calibration, robot: Robot, *, lower_first: bool = True) -> CalibrationResult:
    """Offsets from the sweeps; with ``lower_first`` (the operator swept to the lower stop first) a joint
    whose reading reached its maximum first is flagged as a probable direction flip."""
    max_first = {j for j, first in tracker.order().items() if first == "max"} if lower_first else set()
    calibration, reports = calibrate_from_sweeps(tracker.sweeps(), prior, robot, max_first=max_first)
    return CalibrationResult(calibration, reports, mirror_check(calibration, robot), tracker.rows(), robot)


def merge_phases(results: Sequence[CalibrationResult]) -> CalibrationResult:
    """One result of a run in phases, each on its own joints with the previous one's calibration as its prior:
    the last calibration, each joint's report from the phase that saw it, the sweeps of every phase."""
    last = results[-1]
    reports = {r.joint: r for r in last.reports}
    for result in results[:-1]:
        reports.update({r.joint: r for r in result.reports if r.status is not Status.CARRIED})
    rows = {row.joint: row for result in results for row in result.rows}
    return CalibrationResult(last.calibration, [reports[j] for j in last.robot.names], last.mirror,
                             list(rows.values()), last.robot)


def write(path: str | Path, result: CalibrationResult, robot: Robot, comment: str = "") -> None:
    """Atomic: a reader (or an interrupted run) sees the previous file or the complete new one. ``comment``
    (YAML comment lines) records the run in the file's header."""
    save_calibration(path, result.calibration, robot.hardware, comment=comment)


def plot_sweeps(path: str | Path, result: CalibrationResult, robot: Robot) -> None:
    """One row per swept joint: the described range, and the sweep moved into the joint frame by the new
    offset; after a good calibration the two coincide."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from humanoid_prime.files import atomic_write_bytes

    rows = [r for r in result.rows if r.maximum >= r.minimum]
    if not rows:
        raise PrimeError("nothing was swept, so there is nothing to plot")
    fig, ax = plt.subplots(figsize=(9, 0.45 * len(rows) + 1.2))
    for y, row in enumerate(rows):
        cal = result.calibration.joints[row.joint]
        shift = cal.direction * cal.homing_offset
        ax.plot([row.lower, row.upper], [y, y], color="0.75", linewidth=9, solid_capstyle="butt",
                label="described range" if y == 0 else None)
        ax.plot([row.minimum - shift, row.maximum - shift], [y, y], color="tab:blue", linewidth=3,
                label="sweep, calibrated" if y == 0 else None)
    ax.set_yticks(range(len(rows)), [r.joint for r in rows])
    ax.invert_yaxis()
    ax.set_xlabel("joint angle (rad)")
    ax.set_title("Prime calibration: sweeps against the description's limits")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.6 / (0.45 * len(rows) + 1.2)), ncol=2, fontsize="small",
              frameon=False)  # below the axes, where it hides no bar
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    import io

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())


@dataclass(frozen=True)
class VerifyRow:
    joint: str
    stop: str  # "lower" | "upper"
    limit: float
    reading: float

    @property
    def error(self) -> float:
        return self.reading - self.limit

    @property
    def ok(self) -> bool:
        return math.isfinite(self.reading) and abs(self.error) <= VERIFY_TOLERANCE_RAD

    def as_dict(self) -> dict[str, object]:
        return {"joint": self.joint, "stop": self.stop, "limit": self.limit, "reading": self.reading,
                "error": self.error, "ok": self.ok}
