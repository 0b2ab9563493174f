"""``prime calibrate``: sweep tracker and offset computation for one physical robot (or the virtual one)."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from humanoid_prime.calibration.math import MIN_SWEEP_RAD, Status
from humanoid_prime.calibration.tracker import SweepTracker
from humanoid_prime.calibration.workflow import (
    VERIFY_TOLERANCE_RAD,
    CalibrationResult,
    VerifyRow,
    check_joint_names,
    compute,
    identity_from,
    merge_phases,
    plot_sweeps,
    tracked_joints,
    write,
)
from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import (
    add_config_options,
    add_emulation_options,
    add_json_option,
    add_mailbox_option,
    add_realtime_options,
    add_record_option,
    add_socket_option,
    add_web_option,
    check_web,
    output_file,
    ring_options,
    write_summary,
)
from humanoid_prime.cli._common import console as make_console
from humanoid_prime.cli._live import ModeKeys, flag_lines
from humanoid_prime.cli.addons import Addons, Run
from humanoid_prime.cli.calibrate_auto import add_auto_options, check_auto_options, config_option, run_auto
from humanoid_prime.config.calibration import VIRTUAL_MARK, Calibration, load_calibration, virtual_may_replace
from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.config.location import write_target
from humanoid_prime.config.robot import Robot
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import output_problem
from humanoid_prime.runtime.run import run_loop
from humanoid_prime.runtime.session import (
    BACKENDS,
    BringupOptions,
    Session,
    open_session,
    plan_session,
)
from humanoid_prime.runtime.signals import stop_on_signals
from humanoid_prime.runtime.socket import ControlServer

READOUT_HZ = 5.0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate", help=summary("calibrate"),
        description="Bring up the chosen buses with identity calibration (the prior's directions, offset 0) and "
                    "only the joint-state broadcaster, and track each joint's min/max while you sweep it to both "
                    "mechanical stops, the lower stop first (eRob: `prime limp RING_POS` in another terminal; "
                    "Sito wrists are limp already). Ctrl-C (or q) computes the offsets and writes a complete "
                    "14-joint file atomically, carrying the prior through for joints not swept.")
    p.add_argument("--backends", choices=BACKENDS, default="all", help="which buses to bring up (default all)")
    add_config_options(p, calibration=True, controllers=True)
    p.add_argument("--output", metavar="FILE", type=output_file,
                   help="write the result here instead of the robot's calibration file (which stays the prior)")
    p.add_argument("--prior", metavar="FILE",
                   help="calibration carried through for joints not swept, and the source of the directions "
                        "(default: the file being replaced)")
    add_emulation_options(p, "calibrate the virtual Prime (private network namespace)")
    add_mailbox_option(p)
    p.add_argument("--scripted", nargs="?", const="all", metavar="JOINT,...",
                   help="(with --emulate) a scripted operator sweeps these joints (default: every joint of the "
                        "run) to both stops, then the run ends")
    p.add_argument("--verify", action="store_true",
                   help="instead of calibrating: bring up with the robot's calibration (or --calibration) folded "
                        "and check that each joint at a stop reads that stop's limit (driven on the emulator, by "
                        "you on the robot)")
    p.add_argument("--joints", metavar="JOINT,...",
                   help="the joints to calibrate (or with --verify, to check); default: every joint of the run's "
                        "buses. The run exits non-zero unless each of them was calibrated")
    p.add_argument("--plot", metavar="PNG", type=output_file, help="also draw each joint's sweep against its limits")
    p.add_argument("--any-order", action="store_true",
                   help="the stops were swept in any order: skip the direction check that relies on sweeping "
                        "each joint to its lower stop first")
    add_realtime_options(p, rate_help=None)
    add_socket_option(p)
    add_record_option(p)
    add_web_option(p)
    p.add_argument("--no-live", action="store_true", help="no live readout even on a terminal")
    p.add_argument("--summary", metavar="FILE", type=output_file,
                   help="write the run's result as JSON (what --json prints)")
    add_json_option(p)
    add_auto_options(p)
    # --output refines the calibration it names: it is the run's prior and its result.
    p.set_defaults(func=run, may_overwrite={("output", "calibration"), ("output", "prior")})


def _joint_list(text: str | None) -> list[str]:
    return [j.strip() for j in (text or "").split(",") if j.strip()]


# The documented procedure (DESIGN §5): the eRob arms on EtherCAT first, then the wrists on CAN alone, since
# limp wrists flop while an arm is swept. --backends ec or can runs one of the two phases.
PHASES = {"all": ("ec", "can"), "ec": ("ec",), "can": ("can",)}
PHASE_NAMES = {"ec": "the eRob arms on EtherCAT", "can": "the Sito wrists on CAN"}


def run(args: argparse.Namespace) -> int:
    emulator = ring_options(args, **{"--scripted": args.scripted})
    check_web(args)
    if args.cpu is not None and not args.realtime:
        raise PrimeError("--cpu pins the real-time control thread; it cannot be combined with --no-realtime")
    check_auto_options(args)  # first: --auto --verify is the conflict to name, not what --verify refuses
    if args.verify:
        for option, value in (("--plot", args.plot), ("--output", args.output), ("--prior", args.prior)):
            if value is not None:
                raise PrimeError(f"{option} belongs to a calibration run; --verify checks --calibration and "
                                 "writes nothing")
    files = args.config
    hardware = load_hardware(args.hardware)
    target = Path(args.output) if args.output is not None else write_target(files.calibration, files.folder)
    virtual = bool(args.emulate or getattr(args, "sim", False))
    if virtual and args.output is None and not args.verify and not virtual_may_replace(target, hardware):
        raise PrimeError(f"{target} holds offsets measured on a physical robot, and this run is on a virtual one "
                         "(--emulate or --sim): give --output FILE for its result")
    _check_results_writable(args, target)
    # The prior is the file being replaced, never identity: a run cannot weaken what it did not sweep.
    prior = load_calibration(hardware, args.prior or (target if target.is_file() else args.calibration))
    checked = load_calibration(hardware, args.calibration) if args.verify else None
    robot = plan_session(BringupOptions(hardware_file=args.hardware, controllers_file=args.controllers,
                                        calibration=checked or prior)).robot  # everything checked before a bus
    run_joints = _run_joints(robot, args.backends)
    if args.scripted and args.scripted != "all":
        check_joint_names(robot, _joint_list(args.scripted), run_joints, "--scripted")
    check_joint_names(robot, _joint_list(args.joints), run_joints, "--joints")
    if args.emulate:
        from humanoid_prime.virtual.harness import enter_private_netns

        enter_private_netns()
    if args.auto is not None:
        return run_auto(args, prior, target, emulator)
    if args.verify:
        return _verify(args, checked, emulator)
    asked = tuple(_joint_list(args.joints)) or (
        tuple(_joint_list(args.scripted)) if args.scripted and args.scripted != "all" else run_joints)
    return _calibrate(args, prior, target, asked, emulator)


def _check_results_writable(args: argparse.Namespace, target: Path) -> None:
    """Refuse, before anything moves, a run whose result could not be written at its end: the calibration
    (the robot's own file where --output is not given), and with --apply the hardware file."""
    ends = [] if args.verify else [(target, "the calibration", "give --output FILE")]
    if args.apply:
        ends.append((Path(args.hardware), "--apply's hardware file", "give --hardware FILE"))
    for path, what, fix in ends:
        problem = output_problem(path)
        if problem is not None:
            raise PrimeError(f"{what} could not be written at the end of this run: {problem}; {fix} where it can")


def _run_joints(robot: Robot, backends: str) -> tuple[str, ...]:
    """The joints every phase of a run on ``backends`` tracks, in canonical order."""
    tracked = {joint for phase in PHASES[backends] for joint in tracked_joints(robot, phase)}
    return tuple(joint for joint in robot.names if joint in tracked)


def _virtual(args: argparse.Namespace, ring: dict[str, Any], stack: contextlib.ExitStack) -> Any:
    """The virtual Prime for the whole run with --emulate (None on the robot)."""
    if not args.emulate:
        return None
    from humanoid_prime.virtual.harness import attach_virtual_prime

    return attach_virtual_prime(stack, hardware_file=args.hardware, truth_file=args.truth, ring_options=ring,
                                avoid_cpu=args.cpu)


class _Recording:
    """``--record``: one file for the whole run, each phase's session attached in turn."""

    def __init__(self, args: argparse.Namespace, stack: contextlib.ExitStack) -> None:
        self.args = args
        self.stack = stack
        self.run: Run | None = None

    def attach(self, session: Session, stack: contextlib.ExitStack) -> None:
        if self.run is None:
            # Stamps in the system clock, as on the robot; the file is finished when the run ends.
            self.run = Run(session.manager, report=print, epoch_offset=time.time() - time.monotonic())
            Addons().attach(self.run, self.args, self.stack, names=("record",))
        self.run.follow(session.manager, stack)


class _Web:
    """``--web``: one page for the whole run, showing each phase's joints and the ranges swept so far."""

    def __init__(self, port: int | None, hardware_file: Any, stack: contextlib.ExitStack) -> None:
        self.view = None
        self.phase: tuple[Callable[[], dict[str, Any]], SweepTracker] | None = None  # its state, its sweeps
        self.swept: dict[str, tuple[float, float]] = {}  # the phases before this one
        if port is None:
            return
        from humanoid_prime.config.robot import load_robot
        from humanoid_prime.view.page import PrimeView

        self.robot = load_robot(hardware_file)
        self.view = PrimeView(self.robot, port=port, source=self._state, sweeps=True, title="Prime calibration")
        stack.callback(self.view.close)
        print(f"view: {self.view.url}", flush=True)

    def attach(self, session: Session, tracker: SweepTracker, stack: contextlib.ExitStack) -> None:
        if self.view is None:
            return
        from humanoid_prime.view.feeds import manager_source

        state, detach_state = manager_source(session.manager)
        self.phase = (state, tracker)

        def detach() -> None:
            self.swept.update(tracker.sweeps())
            detach_state()
            self.phase = None

        stack.callback(detach)

    def _state(self) -> dict[str, Any]:
        phase = self.phase
        if phase is None:
            raise ConnectionError("between phases")
        state, tracker = phase
        swept = {**self.swept, **tracker.sweeps()}
        nothing = (float("inf"), float("-inf"))
        return {**state(), "sweeps": [swept.get(name, nothing) for name in self.robot.names]}


def _open(args: argparse.Namespace, backends: str, calibration: Any, virtual: Any, server: ControlServer,
          stack: contextlib.ExitStack) -> Session:
    """A broadcaster-only session on ``backends`` with ``calibration``, answering on ``server``."""
    # The loop keeps every drive's output watchdog fed while the arm is swept: on a busy computer it needs the
    # same real-time scheduling as a bring-up (a 100 ms stall faults every drive with 0xA000).
    options = BringupOptions(backends=backends, calibration=calibration, broadcaster_only=True,
                             emulated=virtual is not None, hardware_file=args.hardware,
                             controllers_file=args.controllers, control_socket=args.socket,
                             realtime=args.realtime, cpu=args.cpu, config=args.config.as_dict(),
                             state_folder=args.config.folder.state, ec_mailbox=args.ec_mailbox)
    if virtual is not None:
        options.interface = virtual.master_interface
        options.can_interface, options.can_channel = virtual.can_interface, virtual.can_channel
    plan = plan_session(options)
    plan.control = server
    return open_session(plan, stack)


class _Readout:
    """The live table: position, min, max, sweep and range coverage per joint, redrawn in place at 5 Hz."""

    def __init__(self, tracker: SweepTracker, console: Console, session: Session, title: str) -> None:
        self.tracker = tracker
        self.console = console
        self.session = session
        self.title = title

    def __rich__(self) -> Group:
        table = Table(title=self.title, title_justify="left", box=None, header_style="bold")
        for column in ("joint", "q rad", "min", "max", "sweep", "range covered"):
            table.add_column(column, justify="left" if column == "joint" else "right")
        for row in self.tracker.rows():
            seen = row.maximum >= row.minimum
            sweep = row.sweep
            style = "green" if sweep >= 0.5 else ("yellow" if seen else "dim")
            bar = "#" * round(10 * min(row.coverage, 1.0))
            table.add_row(row.joint, f"{row.position:+.3f}" if seen else "-",
                          f"{row.minimum:+.3f}" if seen else "-", f"{row.maximum:+.3f}" if seen else "-",
                          Text(f"{sweep:.3f}", style=style), f"{bar:<10} {100 * row.coverage:3.0f}%")
        return Group(*flag_lines(self.session.manager), table)


def _calibrate(args: argparse.Namespace, prior: Calibration, target: Path, asked: tuple[str, ...],
               ring: dict[str, Any]) -> int:
    """Every phase of the procedure in turn, each on its own bus with the previous phase's result as its
    prior; the file is written after each phase that swept something. Enter or n ends a phase and goes on;
    q, Ctrl-C or SIGTERM ends the run (after writing what the phase swept). Exit 0 only when every joint
    asked for was calibrated and no device faulted."""
    console = make_console()
    phases = PHASES[args.backends]
    finish = threading.Event()
    results: list[CalibrationResult] = []
    faults: list[dict[str, Any]] = []
    calibration = prior
    with stop_on_signals(finish), contextlib.ExitStack() as run_stack:
        server = run_stack.enter_context(ControlServer(path=args.socket))  # a second instance stops here
        virtual = _virtual(args, ring, run_stack)
        recording = _Recording(args, run_stack)
        web = _Web(args.web, args.hardware, run_stack)
        for number, backends in enumerate(phases, start=1):
            if finish.is_set():
                break
            title = f"phase {number} of {len(phases)}: {PHASE_NAMES[backends]}"
            result, phase_faults = _phase(args, backends, calibration, virtual, server, finish, console, title,
                                          recording, web)
            faults += [{"phase": title, **fault} for fault in phase_faults]
            if result.swept:
                results.append(result)
                merged = merge_phases(results)
                mark = VIRTUAL_MARK if args.emulate else ""  # another virtual run may replace it, nothing else
                write(target, merged, result.robot, comment=mark + _file_note(merged, asked))
                calibration = result.calibration
    errors = [f"{f['phase']}: {f['key']} at {f['since_s']:.2f} s: {f['text']}" for f in faults
              if f["level"] == "ERROR"]
    if not results:
        raise PrimeError(f"nothing was swept (no joint moved {MIN_SWEEP_RAD} rad or more); {target} was not "
                         "written" + (" and is as it was" if target.exists() else "")
                         + (f"; the run faulted: {errors[0]}" if errors else ""))
    merged = merge_phases(results)
    if args.plot:
        plot_sweeps(args.plot, merged, merged.robot)
    missing = _not_calibrated(merged, asked)
    next_command = _next_command(args, merged, missing, target)
    report = {"output": str(target), "ok": not missing and not errors, "asked": list(asked),
              "not_calibrated": missing, **merged.as_dict(), "faults": faults, "next": next_command}
    write_summary(args, report)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _report(console, merged, str(target))
        for line in errors:
            console.print(Text(f"FAULT {line}", style="bold red"))
    done = len(asked) - len(missing)
    if missing or errors:
        why = [f"{len(missing)} of {len(asked)} joints not calibrated ({', '.join(missing)})"] if missing else []
        why += [f"{len(errors)} fault(s) during the run ({errors[0]})"] if errors else []
        print(f"prime calibrate: NOT complete: {'; '.join(why)}; {target} keeps the prior offsets of joints not "
              f"calibrated. Next: {next_command}", file=sys.stderr)
        return 1
    if not args.json:
        console.print(f"calibrated {done} of {len(asked)} joints. Next: {next_command}")
    return 0


def _not_calibrated(result: CalibrationResult, asked: tuple[str, ...]) -> list[str]:
    """The joints asked for that this run did not calibrate (not swept, too short, or a probable flip)."""
    status = {r.joint: r.status for r in result.reports}
    return [joint for joint in asked if status[joint] is not Status.CALIBRATED]


def _file_note(result: CalibrationResult, asked: tuple[str, ...]) -> str:
    """The calibration file's own record of the run: what was calibrated and what kept its prior offset."""
    by_status: dict[str, list[str]] = {}
    for r in result.reports:
        by_status.setdefault(str(r.status), []).append(r.joint)
    lines = [f"# written by prime calibrate at {time.strftime('%Y-%m-%d %H:%M:%S %z')}"]
    for status, words in ((Status.CALIBRATED, "calibrated in this run"),
                          (Status.PROBABLE_FLIP, "PROBABLE DIRECTION FLIP (offset written, run `prime calibration "
                                                 "flip JOINT`)"),
                          (Status.SKIPPED, "swept too little, prior offset kept"),
                          (Status.CARRIED, "not swept, prior offset kept")):
        joints = by_status.get(str(status), [])
        if joints:
            lines.append(f"# {words}: {', '.join(joints)}")
    missing = _not_calibrated(result, asked)
    if missing:
        lines.append(f"# asked for but not calibrated: {', '.join(missing)}")
    return "\n".join(lines) + "\n"


def _next_command(args: argparse.Namespace, result: CalibrationResult, missing: list[str], target: Path) -> str:
    """The exact command an operator runs next: a flip, the joints still to do, or the bring-up."""
    where = config_option(args, target)
    flips = [r.joint for r in result.reports if r.status is Status.PROBABLE_FLIP and r.joint in missing]
    if flips:
        return f"prime calibration flip {flips[0]}{where}" + (f" (then {', '.join(flips[1:])})" if flips[1:] else "")
    if missing:
        backends = {"ec" if joint in result.robot.hardware.erob_slaves else "can" for joint in missing}
        option = f" --backends {backends.pop()}" if len(backends) == 1 else ""
        return f"prime calibrate{option} --joints {','.join(missing)}{where}"
    return f"prime calibration check{where}, then prime bringup{where}"


def _phase(args: argparse.Namespace, backends: str, prior: Calibration, virtual: Any, server: ControlServer,
           finish: threading.Event, console: Console, title: str, recording: _Recording,
           web: _Web) -> tuple[CalibrationResult, list[dict[str, Any]]]:
    """One phase: bring its bus up with identity calibration, track its joints until it ends, compute."""
    stop = threading.Event()  # this phase ends (the whole run ends too when ``finish`` is set)
    with contextlib.ExitStack() as stack:
        session = _open(args, backends, identity_from(prior), virtual, server, stack)
        recording.attach(session, stack)
        robot = session.robot
        joints = tracked_joints(robot, backends)
        scripted = None
        if args.scripted:
            named = _run_joints(robot, args.backends) if args.scripted == "all" else _joint_list(args.scripted)
            scripted = tuple(j for j in named if j in joints)
        tracker = SweepTracker(robot, joints)
        tracker.attach(session.manager.topics)
        web.attach(session, tracker, stack)
        keys = "Enter or n: done, go on; q or Ctrl-C: write and stop" if backends != PHASES[args.backends][-1] \
            else "Enter, n, q or Ctrl-C: write and stop"
        if "ec" in backends:
            keys += "; r: reset a faulted drive"
        if not args.json:
            console.print(f"{title}: up in {session.bringup_seconds:.2f} s with identity calibration; tracking "
                          f"{len(joints)} joints. Sweep each to its LOWER stop first, then the upper. {keys}.")
        worker = _start_scripted(session, virtual, scripted, stop) if scripted is not None else None
        if console.is_terminal and not args.no_live and not args.json:
            stack.enter_context(Live(_Readout(tracker, console, session, f"prime calibrate, {title}"),
                                     console=console, refresh_per_second=READOUT_HZ))
            if sys.stdin.isatty():
                stack.enter_context(ModeKeys(lambda mode: None, lambda: (finish.set(), stop.set()),
                                             on_reset=session.manager.request_reset,
                                             extra={"n": stop.set, "\n": stop.set}))
        run_loop(session, stop, on_tick=lambda manager: stop.set() if finish.is_set() else None)
        if worker is not None:
            worker.join(timeout=30.0)  # the operator lets go and restores its limp joint before teardown
        result = compute(tracker, prior, robot, lower_first=not args.any_order)
    return result, [f.as_dict() for f in session.faults]


def _start_scripted(session: Session, virtual: Any, joints: tuple[str, ...], stop: threading.Event) -> threading.Thread:
    from humanoid_prime.virtual.operator import ScriptedOperator

    def work() -> None:
        try:
            operator = ScriptedOperator(session, virtual.control, stop=stop)
            operator.by_hand(joints, operator.sweep)
        except Exception as exc:  # reported with the run; the file is still written from what was swept
            session.record_fault("scripted_operator", f"{type(exc).__name__}: {exc}")
        finally:
            stop.set()

    thread = threading.Thread(target=work, name="scripted-operator", daemon=True)
    thread.start()
    return thread


def _report(console: Console, result: CalibrationResult, output: str) -> None:
    console.print(f"wrote {output}")
    for r in result.reports:
        style = {"calibrated": "green", "skipped": "yellow", "probable_flip": "bold red", "carried": "dim"}[r.status]
        if "short of stop to stop" in r.message:
            style = "yellow"
        console.print(Text(f"  {r.joint:<22} {r.status:<13} offset {r.offset:+.4f} rad  {r.message}", style=style))
    console.print("mirror check (left vs right):")
    for m in result.mirror:
        mark = "ok" if m.ok else "CHECK"
        console.print(f"  {m.left:<22} {m.left_offset:+.4f}  {m.right:<22} {m.right_offset:+.4f}  "
                      f"{m.relation:<8} residual {m.residual:+.4f}  {mark}")


def _verify(args: argparse.Namespace, calibration: Any, ring: dict[str, Any]) -> int:
    stop = threading.Event()
    rows: list[VerifyRow] = []
    errors: list[str] = []
    with stop_on_signals(stop), contextlib.ExitStack() as stack:
        server = stack.enter_context(ControlServer(path=args.socket))
        virtual = _virtual(args, ring, stack)
        session = _open(args, args.backends, calibration, virtual, server, stack)
        _Recording(args, stack).attach(session, stack)
        robot = session.robot
        joints = tracked_joints(robot, args.backends)
        chosen = tuple(_joint_list(args.joints)) or joints
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


def _verify_joints(session: Session, virtual: Any, joints: tuple[str, ...], rows: list[VerifyRow],
                   errors: list[str], stop: threading.Event) -> None:
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
