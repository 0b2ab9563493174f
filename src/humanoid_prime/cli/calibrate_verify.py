"""``prime calibrate --verify``: each joint held at its stops (by the scripted operator on the virtual Prime, by
the operator on the robot), its reading beside its limit."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
import time
from typing import TYPE_CHECKING

from humanoid_prime.calibration.workflow import VERIFY_TOLERANCE_RAD, VerifyRow, check_joint_names, tracked_joints
from humanoid_prime.cli._common import console as make_console
from humanoid_prime.cli._common import write_summary
from humanoid_prime.cli.calibrate_session import Recording, joint_list, open_phase, virtual_prime
from humanoid_prime.config.calibration import Calibration
from humanoid_prime.config.robot import Robot
from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.run import run_loop
from humanoid_prime.runtime.session import Session
from humanoid_prime.runtime.signals import stop_on_signals
from humanoid_prime.runtime.socket import ControlServer

if TYPE_CHECKING:
    from humanoid_prime.virtual.harness import VirtualPrime
    from humanoid_prime.virtual.ring.options import RingSettings


def verify(args: argparse.Namespace, calibration: Calibration, ring: RingSettings) -> int:
    stop = threading.Event()
    rows: list[VerifyRow] = []
    errors: list[str] = []
    with stop_on_signals(stop), contextlib.ExitStack() as stack:
        server = stack.enter_context(ControlServer(path=args.socket))
        virtual = virtual_prime(args, ring, stack)
        session = open_phase(args, args.backends, calibration, virtual, server, stack)
        Recording(args, stack).attach(session, stack)
        robot = session.robot
        joints = tracked_joints(robot, args.backends)
        chosen = tuple(joint_list(args.joints)) or joints
        check_joint_names(robot, chosen, joints, "--joints")
        worker = threading.Thread(target=_verify_joints, args=(session, virtual, chosen, rows, errors, stop),
                                  name="verify", daemon=True)
        worker.start()
        if not args.json and virtual is not None:  # the scripted check runs on its own: show how far it is
            from humanoid_prime.cli._live import Working

            working = stack.enter_context(Working(make_console(), "verifying the stops", total=2 * len(chosen)))
            run_loop(session, stop, on_tick=lambda manager: working.update(
                f"verifying the stops: {rows[-1].joint if rows else chosen[0]}", completed=len(rows)))
        else:
            run_loop(session, stop)
        worker.join(timeout=30.0)
    if errors:
        raise PrimeError(errors[0])
    ok = len(rows) == 2 * len(chosen) and all(r.ok for r in rows)  # every stop of every joint, each within tolerance
    report = {"tolerance_rad": VERIFY_TOLERANCE_RAD, "ok": ok, "rows": [r.as_dict() for r in rows]}
    write_summary(args, report)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for r in rows:
            print(f"{r.joint:<22} {r.stop:<5} limit {r.limit:+.4f}  reads {r.reading:+.4f}  "
                  f"error {1e3 * r.error:+7.2f} mrad  {'ok' if r.ok else 'FAIL'}")
        if len(rows) < 2 * len(chosen):
            print(f"NOT verified: {len(rows)} of {2 * len(chosen)} stops were checked")
        print(("verified: every joint reads its limit within " if ok else "NOT verified: readings off by more than ")
              + f"{1e3 * VERIFY_TOLERANCE_RAD:g} mrad")
    return 0 if ok else 1


def _verify_joints(session: Session, virtual: VirtualPrime | None, joints: tuple[str, ...],
                   rows: list[VerifyRow], errors: list[str], stop: threading.Event) -> None:
    robot: Robot = session.robot
    try:
        if virtual is not None:
            from humanoid_prime.virtual.operator import ScriptedOperator

            operator = ScriptedOperator(session, virtual.control, stop=stop)

            def check(joint: str) -> None:
                spec = robot.joints[robot.index(joint)]
                lower, upper = operator.stops(joint)
                rows.extend((VerifyRow(joint, "lower", spec.lower, lower),
                             VerifyRow(joint, "upper", spec.upper, upper)))

            try:
                operator.by_hand(joints, check)
            finally:  # both hands' rows in the order of the joints asked for, each lower stop first
                rows.sort(key=lambda row: (joints.index(row.joint), row.stop != "lower"))
        else:
            position = session.manager.resources.state.position
            for joint in joints:
                spec = robot.joints[robot.index(joint)]
                for name, limit in (("lower", spec.lower), ("upper", spec.upper)):
                    hint = (f" (limp it first: prime limp {spec.ring_position})" if spec.family == "erob" else "")
                    print(f"Hold {joint} against its {name} stop{hint}, then press Enter", flush=True)
                    if not sys.stdin.readline():
                        raise PrimeError("stdin closed before every stop was checked")
                    time.sleep(0.1)
                    rows.append(VerifyRow(joint, name, limit, float(position[spec.index])))
    except Exception as exc:
        errors.append(f"verify: {exc}")
    finally:
        stop.set()
