"""The robot's checks: its configuration folder and files (each loaded as every command loads it, with its
sha256), a calibration that is a robot's and not the identity template, directions that fold into the eRob
configs as they should, and the last run's summary with what it flagged.

Runs write a summary only when asked (``--summary FILE`` on bringup, sim, calibrate and the rest), so the doctor
reads the one named with ``--last-run FILE``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from humanoid_prime.calibration.math import FLIP_OFFSET_RAD, probable_flips
from humanoid_prime.config.calibration import Calibration, is_virtual, load_calibration
from humanoid_prime.config.controllers import ControllersConfig, load_controllers
from humanoid_prime.config.location import ConfigFile, ConfigFiles
from humanoid_prime.config.robot import JointSpec, Robot, load_robot
from humanoid_prime.doctor.report import Check, failed, not_run, passed, warned
from humanoid_prime.doctor.system import Json, member
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD
from humanoid_prime.drivers.ethercat.fold import check_foldable, fold_slave_config
from humanoid_prime.drivers.ethercat.slave_config import SlaveConfig, load_slave_config, parse_slave_config
from humanoid_prime.errors import PrimeError

GROUP = "robot"


@dataclass
class Loaded:
    """The robot's files as loaded (None where one did not load)."""

    robot: Robot | None = None
    calibration: Calibration | None = None
    controllers: ControllersConfig | None = None


def _file(config: ConfigFile) -> str:
    return f"{config.path} ({config.why}), sha256 {config.sha256()[:16]}"


def config_checks(files: ConfigFiles) -> tuple[list[Check], Loaded]:
    """The folder and the three files, each loaded; what loaded is returned for the other checks."""
    folder = files.folder
    checks = []
    if folder.path.is_dir():
        checks.append(passed(GROUP, "folder", f"{folder.path} ({folder.why})"))
    else:
        checks.append(warned(GROUP, "folder", f"no config folder {folder.path} ({folder.why}): every file is the "
                                              "bundled template", folder.init_command()))
    loaded = Loaded()
    try:
        loaded.robot = load_robot(files.hardware.path)
    except PrimeError as exc:
        checks.append(failed(GROUP, "hardware", str(exc), f"fix {files.hardware.path}"))
    else:
        if files.hardware.template:
            checks.append(warned(GROUP, "hardware", f"the bundled template {files.hardware.path}: its buses "
                                                    f"(ethercat {loaded.robot.hardware.ethercat.interface}, can "
                                                    f"{loaded.robot.hardware.can.channel}) are no robot's",
                                 f"{folder.init_command()}, then set buses in prime_hardware.yaml"))
        else:
            checks.append(passed(GROUP, "hardware", _file(files.hardware)))
    if loaded.robot is None:
        checks += [not_run(GROUP, name, "the hardware file did not load") for name in ("calibration_file",
                                                                                       "controllers")]
        return checks, loaded
    try:
        loaded.calibration = load_calibration(loaded.robot.hardware, files.calibration.path)
        checks.append(passed(GROUP, "calibration_file", _file(files.calibration)))
    except PrimeError as exc:
        checks.append(failed(GROUP, "calibration_file", str(exc), f"fix {files.calibration.path}, or calibrate "
                                                                  "again: prime calibrate --auto"))
    try:
        loaded.controllers = load_controllers(loaded.robot.names, files.controllers.path)
        checks.append(passed(GROUP, "controllers", f"{_file(files.controllers)}, update_rate "
                                                   f"{loaded.controllers.update_rate:g} Hz"))
    except PrimeError as exc:
        checks.append(failed(GROUP, "controllers", str(exc), f"fix {files.controllers.path}"))
    return checks, loaded


def calibration_check(calibration: Calibration, config: ConfigFile) -> Check:
    """A robot's own calibration: not the bundled template, not every offset 0, not a virtual run's."""
    fix = "prime calibrate --auto (hands-free), or prime calibrate (by hand)"
    if config.template:
        return failed(GROUP, "calibration", f"the bundled identity template ({config.path}): no joint is "
                                            "calibrated, modes that move a joint are refused on the robot", fix)
    if calibration.is_identity:
        return failed(GROUP, "calibration", f"{config.path} is the identity: every homing_offset is 0, as no "
                                            "calibrated robot reads", fix)
    if is_virtual(config.path):
        return warned(GROUP, "calibration", f"{config.path} was written by a run on a virtual robot (--emulate or "
                                            "--sim), not on this one", fix)
    flipped = sum(1 for c in calibration.joints.values() if c.direction < 0)
    return passed(GROUP, "calibration", f"{config.path}: {len(calibration.joints)} joints, {flipped} with direction "
                                        "-1, offsets measured")


def _round_trip(spec: JointSpec, folded: SlaveConfig) -> str | None:
    """Why the fold does not read each limit back through the drive's counts (None: it does, to a count)."""
    command, state = folded.command("position"), folded.state("position")
    for q in (spec.lower, spec.upper):
        back = state.state_value(command.command_raw(q))
        if abs(back - q) > 1.0 / COUNTS_PER_RAD:
            return f"{q:+.3f} rad is commanded as {command.command_raw(q)} counts, which read back as {back:+.3f}"
    return None


def directions_check(robot: Robot, calibration: Calibration, folded_dir: Path | None = None) -> Check:
    """The calibration's eRob directions and offsets as the fold carries them into the per-slave configs (those
    in ``folded_dir`` when given: the C++ stack's), each limit read back through the fold; offsets past half a
    turn (a probable direction flip)."""
    try:
        check_foldable(robot, calibration)
    except PrimeError as exc:
        return failed(GROUP, "directions", str(exc), "prime calibrate --auto")
    problems, stale = [], []
    erob = [spec for spec in robot.joints if spec.family == "erob"]
    for spec in erob:
        cal = calibration.joints[spec.name]
        try:
            if folded_dir is not None:
                folded = load_slave_config(folded_dir / f"{spec.name}.yaml")
            else:
                folded = parse_slave_config(fold_slave_config(spec, cal), f"the fold of {spec.name}")
            position = folded.state("position")
        except (PrimeError, OSError) as exc:
            problems.append(f"{spec.name}: {exc}")
            continue
        direction = 1 if position.factor > 0 else -1
        offset = -position.offset * direction
        if direction != cal.direction or not math.isclose(offset, cal.homing_offset, abs_tol=1e-9):
            stale.append(f"{spec.name} folded with direction {direction:+d}, offset {offset:+.4f}; the calibration "
                         f"says {cal.direction:+d}, {cal.homing_offset:+.4f}")
            continue
        trip = _round_trip(spec, folded)
        if trip is not None:
            problems.append(f"{spec.name}: {trip}")
    where = f"the configs in {folded_dir}" if folded_dir is not None else "the eRob configs the bring-up folds"
    if stale:
        return failed(GROUP, "directions", f"{where} are not this calibration's: {'; '.join(stale)}",
                      f"prime calibration fold --output {folded_dir}")
    if problems:
        return failed(GROUP, "directions", f"{where}: {'; '.join(problems)}",
                      f"prime calibration fold --output {folded_dir}" if folded_dir is not None
                      else "prime calibrate --auto")
    flips = probable_flips(calibration)
    minus = [spec.name for spec in erob if calibration.joints[spec.name].direction < 0]
    text = (f"{where} carry each joint's direction and offset, every limit reads back to a count "
            f"({len(erob)} eRob; direction -1: {', '.join(minus) or 'none'})")
    if flips:
        return warned(GROUP, "directions", f"{text}; |homing_offset| over {FLIP_OFFSET_RAD:.4f} rad (half a turn, "
                                           f"probably a wrong direction) on {', '.join(flips)}",
                      f"prime calibration flip {flips[0]}, or sweep it again")
    return passed(GROUP, "directions", text)


def read_summary(path: Path) -> Json:
    """The run summary at ``path`` (what a run's ``--summary`` wrote); PrimeError, in one line, when it is none."""
    try:
        summary: object = json.loads(path.read_text())
    except OSError as exc:
        raise PrimeError(f"--last-run {path}: {exc.strerror}") from None
    except ValueError as exc:
        raise PrimeError(f"--last-run {path} is no run summary (not JSON: {exc}); name the file a run's --summary "
                         "wrote") from None
    if not isinstance(summary, dict) or "ok" not in summary:
        raise PrimeError(f"--last-run {path} is no run summary (it has no 'ok'); name the file a run's --summary "
                         "wrote")
    return summary


def last_run_check(path: Path | None, summary: Json | None, files: ConfigFiles) -> Check:
    """The last run's summary (``read_summary``): whether it ended ok, what it flagged, and the files that changed
    since it read them."""
    if path is None or summary is None:
        return passed(GROUP, "last_run", "no run summary named (a run writes one with --summary FILE; the doctor "
                                         "reads it with --last-run FILE)")
    listed = summary.get("problems")
    problems = [str(p) for p in listed] if isinstance(listed, list) else []
    raised = summary.get("faults")
    faults = [f"{f.get('key')}: {f.get('text')}" for f in (raised if isinstance(raised, list) else [])
              if isinstance(f, dict)]
    changed = []
    for kind, used in member(summary, "config").items():
        now = getattr(files, kind, None)
        if isinstance(used, dict) and isinstance(now, ConfigFile) and used.get("sha256") \
                and used["sha256"] != now.sha256():
            changed.append(f"{kind} (the run read {used.get('path')}, sha256 {str(used['sha256'])[:16]})")
    text = f"{path}: {'ended ok' if summary['ok'] else 'not ok'}"
    if faults:
        text += f"; flagged {'; '.join(faults)}"
    if changed:
        text += f"; files changed since: {', '.join(changed)}"
    if problems:
        return warned(GROUP, "last_run", f"{text}; problems: {'; '.join(problems)}",
                      "the lines above point at most causes; the run's summary lists each fault with its time")
    if faults or changed:
        return warned(GROUP, "last_run", text)
    return passed(GROUP, "last_run", text)


def robot_checks(files: ConfigFiles, *, last_run: Path | None = None, summary: Json | None = None,
                 folded_dir: Path | None = None) -> tuple[list[Check], Loaded]:
    checks, loaded = config_checks(files)
    if loaded.calibration is not None and loaded.robot is not None:
        checks += [calibration_check(loaded.calibration, files.calibration),
                   directions_check(loaded.robot, loaded.calibration, folded_dir)]
    else:
        checks += [not_run(GROUP, name, "the calibration did not load") for name in ("calibration", "directions")]
    checks.append(last_run_check(last_run, summary, files))
    return checks, loaded
