"""``prime calibration fold|flip|check``: work with a calibration file without touching the robot."""

from __future__ import annotations

import argparse
from pathlib import Path

from humanoid_prime.calibration.math import FLIP_OFFSET_RAD, flip_direction, mirror_check, probable_flips
from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_config_options, add_hidden_alias, add_json_option, output_dir, print_json
from humanoid_prime.config.calibration import VIRTUAL_MARK, is_virtual, load_calibration, save_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.location import write_target
from humanoid_prime.config.robot import load_robot
from humanoid_prime.drivers.ethercat.fold import write_folded_configs
from humanoid_prime.errors import PrimeError


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("calibration", help=summary("calibration"),
                              description="Work with a calibration file (direction and homing_offset per joint).")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)

    fold = actions.add_parser("fold", help="write the per-slave eRob configs with the calibration folded in",
                              description="Write <joint>.yaml for every eRob joint into DIR: the generic CiA402 "
                                          "slave config of ethercat_driver_ros2 with direction and homing_offset "
                                          "folded into the PDO factors and offsets (no drive NVM is written), and "
                                          "the start-up SDOs that arm the bus gains with the controllers file's "
                                          "standby stiffness. Drive faults latch (auto_fault_reset: false).")
    add_config_options(fold, calibration=True, controllers=True)
    fold.add_argument("--output", metavar="DIR", type=output_dir, help="folder for the per-slave configs")
    add_hidden_alias(fold, "--out", "output", kind=output_dir)
    add_json_option(fold)
    fold.set_defaults(func=_fold)

    flip = actions.add_parser("flip", help="flip one joint's direction without a re-sweep (rewrites the file)",
                              description="Negate JOINT's direction and recompute its offset from the described "
                                          "limits (offset + direction*(lower + upper)), then rewrite the robot's "
                                          "calibration file atomically (the bundled template is never written: "
                                          "without a calibration of its own the robot gets one in its config "
                                          "folder).")
    flip.add_argument("joint", metavar="JOINT")
    add_config_options(flip, calibration=True)
    add_json_option(flip)
    flip.set_defaults(func=_flip)

    check = actions.add_parser("check", help="validate a calibration file, flag probable flips, mirror report",
                               description="Load and validate a calibration file, flag offsets beyond half a turn "
                                           "(probable direction flips) and compare the arms' offsets. Exits 1 "
                                           "when a joint is flagged.")
    check.add_argument("file", nargs="?", metavar="FILE",
                       help="calibration file (default: the robot's, as --calibration)")
    add_config_options(check, calibration=True)
    add_json_option(check)
    check.set_defaults(func=_check)


def _fold(args: argparse.Namespace) -> int:
    if args.output is None:
        raise PrimeError("give --output DIR, the folder for the per-slave configs")
    robot = load_robot(args.hardware)
    calibration = load_calibration(robot.hardware, args.calibration)
    controllers = load_controllers(robot.names, args.controllers)
    out = Path(args.output)
    try:
        paths = write_folded_configs(robot, calibration, out, controllers)
    except OSError as exc:
        raise PrimeError(f"cannot write into {out}: {exc.strerror}") from None
    rows = [{"joint": j.name, "ring_position": j.ring_position, "path": str(path)}
            for j, path in zip((j for j in robot.joints if j.family == "erob"), paths, strict=True)]
    if args.json:
        print_json(rows)
    else:
        print(f"folded {calibration.path} into {len(rows)} eRob slave configs in {out}")
        for r in rows:
            print(f"  ring {r['ring_position']}  {r['path']}")
    return 0


def _flip(args: argparse.Namespace) -> int:
    robot = load_robot(args.hardware)
    calibration = load_calibration(robot.hardware, args.calibration)
    try:
        spec = robot.joints[robot.index(args.joint)]
    except KeyError as exc:
        raise PrimeError(exc.args[0]) from None
    old = calibration.joints[spec.name]
    new = flip_direction(old, spec.lower, spec.upper)
    target = write_target(args.config.calibration, args.config.folder)
    keep = VIRTUAL_MARK if calibration.path is not None and is_virtual(Path(calibration.path)) else ""
    save_calibration(target, calibration.with_joint(spec.name, new), robot.hardware, comment=keep)
    result = {"joint": spec.name, "file": str(target), "read": str(calibration.path),
              "old": {"direction": old.direction, "homing_offset": old.homing_offset},
              "new": {"direction": new.direction, "homing_offset": new.homing_offset}}
    if args.json:
        print_json(result)
    else:
        print(f"{spec.name}: direction {old.direction:+d} -> {new.direction:+d}, homing_offset "
              f"{old.homing_offset:+.6f} -> {new.homing_offset:+.6f} rad (limits [{spec.lower}, {spec.upper}]); "
              f"wrote {target}" + ("" if target == calibration.path else f" (from {calibration.path})"))
    return 0


def _check(args: argparse.Namespace) -> int:
    robot = load_robot(args.hardware)
    calibration = load_calibration(robot.hardware, args.file or args.calibration)
    flags = [{"joint": name, "homing_offset": calibration.joints[name].homing_offset,
              "problem": f"|homing_offset| is over pi ({FLIP_OFFSET_RAD:.4f} rad): probably a direction flip",
              "fix": f"prime calibration flip {name}, or re-sweep with the other direction"}
             for name in probable_flips(calibration)]
    mirror = [{"left": r.left, "right": r.right, "left_offset": r.left_offset, "right_offset": r.right_offset,
               "relation": r.relation, "residual": r.residual, "ok": r.ok}
              for r in mirror_check(calibration, robot)]
    if args.json:
        print_json({"file": str(calibration.path), "valid": True, "flags": flags, "mirror": mirror})
    else:
        print(f"{calibration.path}: valid, {len(calibration.joints)} joints")
        for f in flags:
            print(f"  FLAG {f['joint']}: homing_offset {f['homing_offset']:+.4f}; {f['problem']} ({f['fix']})")
        print("  mirror check (left vs right offsets):")
        for m in mirror:
            mark = "ok" if m["ok"] else "check"
            print(f"    {m['left']:<20} {m['left_offset']:+.4f}  {m['right']:<21} {m['right_offset']:+.4f}  "
                  f"expected {m['relation']:<8} residual {m['residual']:+.4f}  {mark}")
    return 1 if flags else 0
