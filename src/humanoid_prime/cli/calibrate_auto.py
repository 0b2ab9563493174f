"""``prime calibrate --auto``: the hands-free calibration (DESIGN §5, ``calibration.auto``) on the robot, on the
virtual Prime (``--emulate``) or in MuJoCo alone (``--sim``, in virtual time, the model's own stops).

The run is one broadcaster-only session on the buses of the joints asked for; the procedure commands the joints
itself from the control loop and runs its sequence (drive settings, the operator) beside it. On the robot each
joint waits for the operator's Enter (anything else skips it), and any key during a motion stops the run; the
virtual Prime's operator lets every joint move and answers the direction question by watching the joint.
The calibration file is written atomically and completely (the prior kept for every joint not done); with
``--apply`` the measured eRob torque efficiencies go into the hardware file. Exit status 0 only when every joint
asked for was calibrated.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import queue
import select
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import numpy as np
import numpy.typing as npt
from rich.console import Console
from rich.text import Text

from humanoid_prime.calibration.approach import MAX_SPEED_RAD_S
from humanoid_prime.calibration.auto import AutoCalibration
from humanoid_prime.calibration.gravity import GravityModel
from humanoid_prime.calibration.journal import OverrideJournal
from humanoid_prime.calibration.operator import Operator
from humanoid_prime.calibration.report import AutoResult
from humanoid_prime.calibration.sequence import LoopTicks, SteppedTicks
from humanoid_prime.calibration.workflow import check_joint_names, identity_from, tracked_joints
from humanoid_prime.cli._common import console as make_console
from humanoid_prime.cli._common import print_json, real, write_summary
from humanoid_prime.cli.addons import Addons, Run
from humanoid_prime.config.calibration import VIRTUAL_MARK, Calibration, JointCalibration, save_calibration
from humanoid_prime.config.hardware import HardwareConfig, write_erob_torque_efficiency
from humanoid_prime.config.robot import Robot
from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.session import BringupOptions, open_session, plan_session
from humanoid_prime.runtime.signals import stop_on_signals
from humanoid_prime.runtime.socket import ControlServer

if TYPE_CHECKING:
    from humanoid_prime.virtual.ring.options import RingSettings

OVERRIDE_WAY = "master"  # the journal's way for the run's own EtherCAT master (session.restore_left_overrides)
EFFICIENCY_PLAUSIBLE = (0.3, 1.05)  # a measured realised/nominal outside this is not written by --apply
JOIN_TIMEOUT_S = 60.0  # the sequence's restore after the loop was told to stop
SETTLE_S = 1.0  # MuJoCo alone: the arms held this long before the first joint moves


def add_auto_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--auto", nargs="*", metavar="JOINT",
                        help="hands-free: drive each joint (default: every joint of the run, distal to proximal) "
                             "gently into both of its mechanical stops under a capped effort, one joint of each arm at "
                             "a time, and find its offset and direction; on the robot each pair waits for Enter")
    parser.add_argument("--speed", type=real(above=0.0, at_most=MAX_SPEED_RAD_S), metavar="RAD_S",
                        help=f"(with --auto) how fast a joint moves where its stop may be (default and most: "
                             f"{MAX_SPEED_RAD_S:g} rad/s)")
    parser.add_argument("--measure-impedance", action="store_true",
                        help="(with --auto) push each joint against its stops to measure its realised stiffness and "
                             "damping (--apply does too)")
    parser.add_argument("--assume-direction", action="store_true",
                        help="(with --auto) where the physics cannot tell a joint's direction (a symmetric wrist), "
                             "keep the prior's instead of asking after one small motion")
    parser.add_argument("--apply", action="store_true",
                        help="(with --auto) write each eRob joint's measured torque efficiency into the hardware "
                             "file (--hardware FILE)")
    parser.add_argument("--sim", action="store_true",
                        help="(with --auto) in MuJoCo alone, in virtual time, on the model's own stops")


def check_auto_options(args: argparse.Namespace) -> None:
    """Options that only go with --auto, and those that do not go with it; one line each."""
    if args.auto is None:
        used = [name for name, value in (("--speed", args.speed), ("--assume-direction", args.assume_direction),
                                         ("--apply", args.apply), ("--measure-impedance", args.measure_impedance),
                                         ("--sim", args.sim)) if value]
        if used:
            raise PrimeError(f"{', '.join(used)}: only with --auto")
        return
    clashes = [name for name, value in (("--verify", args.verify), ("--scripted", args.scripted),
                                        ("--any-order", args.any_order), ("--web", args.web)) if value]
    if clashes:
        raise PrimeError(f"--auto does not go with {', '.join(clashes)}")
    if args.sim and args.emulate:
        raise PrimeError("--sim and --emulate are two different virtual robots; give one")
    if args.apply and args.config.hardware.template:
        raise PrimeError("--apply writes the measured efficiencies into the robot's hardware file, and this run "
                         f"reads the bundled read-only template: run `{args.config.folder.init_command()}` first, "
                         "or give --hardware FILE")


def config_option(args: argparse.Namespace, target: Path) -> str:
    """The options by which the next command finds the calibration file this run wrote."""
    if args.output is not None or args.config.calibration.why == "--calibration":
        return f" --calibration {target}"
    return f" --robot {args.robot}" if args.robot else ""


def next_after_auto(args: argparse.Namespace, result: AutoResult, target: Path) -> str:
    """The exact command an operator runs next: the joints still to do, or the check and the bring-up."""
    where = config_option(args, target)
    missing = [j for j in result.asked if not result.outcomes[j].done]
    if missing:
        return f"prime calibrate --auto {' '.join(missing)}{where}"
    return f"prime calibration check{where}, then prime bringup{where}"


def run_auto(args: argparse.Namespace, prior: Calibration, output: Path, ring: RingSettings) -> int:
    """The whole --auto run, writing the calibration to ``output``; the exit status."""
    console = make_console()
    result = _in_simulation(args, prior, console) if args.sim else _on_buses(args, prior, ring, console)
    robot = result.robot
    done = [j for j in result.asked if result.outcomes[j].done]
    written = bool(done)
    if written:
        save_calibration(output, result.calibration, robot.hardware,
                         comment=VIRTUAL_MARK if args.emulate or args.sim else "")
    applied = _apply(args, result) if args.apply else {}
    if args.plot:
        from humanoid_prime.calibration.auto_plot import plot_auto

        plot_auto(args.plot, result)
    report = {"output": str(output) if written else None, **result.as_dict(), "applied": applied,
              "next": next_after_auto(args, result, output)}
    write_summary(args, report)
    if args.json:
        print_json(report)
    else:
        _report(console, result, output, written, applied, args.hardware)
        console.print(f"Next: {next_after_auto(args, result, output)}")
    return 0 if result.complete else 1


def _measure(args: argparse.Namespace) -> bool:
    """The stiffness pushes: only where they were asked for."""
    return bool(args.apply or args.measure_impedance)


def _joints(args: argparse.Namespace, robot: Robot, on_run: Sequence[str]) -> tuple[str, ...]:
    chosen = tuple(args.auto) or tuple(on_run)
    check_joint_names(robot, chosen, on_run, "--auto")
    return chosen


def _in_simulation(args: argparse.Namespace, prior: Calibration, console: Console) -> AutoResult:
    """MuJoCo alone at the hardware's control rate, ticked as fast as it computes: the model's stops, the
    identity calibration as the truth."""
    from humanoid_prime.config.robot import load_robot
    from humanoid_prime.sim.demo import START_POSE, build_simulation
    from humanoid_prime.virtual.operator import WatchingOperator

    plan = plan_session(BringupOptions(hardware_file=args.hardware, controllers_file=args.controllers,
                                       calibration=prior))
    robot, config = plan.robot, plan.config
    joints = _joints(args, robot, robot.names)
    # At the hardware's control rate, on the description's simulated block.
    system, manager = build_simulation(load_robot(args.hardware, use_sim=True), config, initial_pose=START_POSE,
                                       update_rate=config.update_rate, broadcaster_only=True, clock=time.monotonic)
    manager.start(now=system.sim_time)
    model = GravityModel(robot)
    try:
        def angles() -> dict[str, float]:
            return {j: float(system.data.qpos[system.qpos_adr[k]]) for k, j in enumerate(robot.names)}

        # The simulated joints are in the model's own frame: the run's prior is the identity, and it is the truth
        # (the gate knows every body from the start). MuJoCo's arms begin limp: held up a second before anything
        # moves, as a robot's drives hold its arms when a calibration begins.
        identity = Calibration({j: JointCalibration() for j in prior.joints})
        auto = AutoCalibration(manager, identity, joints, ticks=SteppedTicks(lambda: manager.tick(now=system.sim_time)),
                               operator=WatchingOperator(robot, angles, model), speed=args.speed or MAX_SPEED_RAD_S,
                               assume_direction=args.assume_direction, report=None if args.json else console.print,
                               model=model, frame_known=True, settle_s=SETTLE_S, measure=_measure(args))
        auto.attach()
        try:
            return auto.run()
        finally:
            auto.detach()
    finally:
        manager.shutdown()


def _on_buses(args: argparse.Namespace, prior: Calibration, ring: RingSettings, console: Console) -> AutoResult:
    """One broadcaster-only session on ``--backends`` with the prior's directions and offsets 0; the procedure in
    the loop and its sequence in a thread beside it."""
    finish = threading.Event()
    with stop_on_signals(finish), contextlib.ExitStack() as stack:
        server = stack.enter_context(ControlServer(path=args.socket))
        virtual = None
        if args.emulate:
            from humanoid_prime.virtual.harness import attach_virtual_prime

            virtual = attach_virtual_prime(stack, hardware_file=args.hardware, truth_file=args.truth,
                                           ring_options=ring)
        # The loop real-time as in bringup: on a busy machine a loop at normal priority misses the ring's frames.
        options = BringupOptions(backends=args.backends, calibration=identity_from(prior), broadcaster_only=True,
                                 realtime=True, emulated=virtual is not None, hardware_file=args.hardware,
                                 controllers_file=args.controllers, control_socket=args.socket,
                                 state_folder=args.config.folder.state, ec_mailbox=args.ec_mailbox)
        if virtual is not None:
            virtual.wire_into(options)
        plan = plan_session(options)
        plan.control = server
        robot = plan.robot
        on_run = tracked_joints(robot, args.backends)
        joints = _joints(args, robot, on_run)
        if virtual is None and not sys.stdin.isatty():
            raise PrimeError("--auto on the robot waits for the operator at each joint: run it at a terminal at the "
                             "robot (stdin is not one)")
        model = GravityModel(robot)  # compiled before the buses run: their keeper must never wait for it
        session = open_session(plan, stack)
        # Stamps in the system clock, as on the robot; the file is finished when the run ends.
        Addons().attach(Run(session.manager, report=print, epoch_offset=time.time() - time.monotonic()), args, stack,
                        names=("record",))
        manager = session.manager
        master = session.ethercat.master if session.ethercat is not None else None
        rings = {j: (master, robot.hardware.erob_slaves[j]) for j in robot.hardware.erob_joints
                 if master is not None and j in on_run}
        ticks = LoopTicks()
        manager.add_end_of_tick(ticks.ticked)
        report = None if args.json else console.print
        if virtual is not None:
            from humanoid_prime.virtual.operator import WatchingOperator

            operator: Operator = WatchingOperator(robot, virtual.control.joints, model)
        else:
            operator = stack.enter_context(TerminalOperator(console))
        # What an eRob's override found is recorded first, so that the next run on this robot restores a drive a
        # killed run left on its approach gains (an emulated ring is new each time: nothing to record).
        journal = None if virtual is not None else OverrideJournal(args.config.folder.state, OVERRIDE_WAY,
                                                                     "prime calibrate --auto")
        auto = AutoCalibration(manager, prior, joints, rings=rings, operator=operator, ticks=ticks,
                               speed=args.speed or MAX_SPEED_RAD_S, assume_direction=args.assume_direction,
                               report=report, model=model, measure=_measure(args), journal=journal)
        if isinstance(operator, TerminalOperator):
            operator.on_key = auto.abort
        auto.attach()
        stack.callback(auto.detach)
        outcome: list[AutoResult] = []
        failures: list[BaseException] = []
        stop = threading.Event()

        def sequence() -> None:
            try:
                outcome.append(auto.run())
            except BaseException as exc:  # raised below, in this thread
                failures.append(exc)
            finally:
                stop.set()

        worker = threading.Thread(target=sequence, name="auto-calibration", daemon=True)
        worker.start()

        def on_tick(_manager: object) -> None:
            if finish.is_set():
                auto.abort("stopped by a signal")

        from humanoid_prime.runtime.run import run_loop

        try:  # real-time: the start-up heap frozen, collections only between ticks (runtime/realtime.py)
            run_loop(session, stop, on_tick=on_tick, report=report)
        finally:
            ticks.stopped.set()
            worker.join(JOIN_TIMEOUT_S)
        if failures:
            raise failures[0]
        if not outcome:
            raise PrimeError("the hands-free calibration did not finish restoring the drives within "
                             f"{JOIN_TIMEOUT_S:g} s; check their gains (prime gains) before the next run")
        return outcome[0]


class TerminalOperator:
    """The person at the robot, at this terminal (cbreak mode): Enter moves a joint, any other key skips it; a key
    pressed while a joint moves stops the run (``on_key``); questions are answered with y or n."""

    answered_by = "the operator's answer"

    def __init__(self, console: Console, stream: TextIO | None = None) -> None:
        self.console = console
        self.stream = stream if stream is not None else sys.stdin
        self.on_key: Callable[[str], None] | None = None
        self._keys: queue.Queue[str] = queue.Queue()
        self._asking = threading.Event()
        self._stop = threading.Event()
        self._saved: list[int | list[bytes | int]] | None = None
        self._thread: threading.Thread | None = None

    def __enter__(self) -> TerminalOperator:
        import termios
        import tty

        fd = self.stream.fileno()
        self._saved = termios.tcgetattr(fd)
        tty.setcbreak(fd)
        self._thread = threading.Thread(target=self._read, args=(fd,), name="auto-keys", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        import termios

        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
        if self._saved is not None:
            with contextlib.suppress(termios.error, OSError):
                termios.tcsetattr(self.stream.fileno(), termios.TCSADRAIN, self._saved)

    def _read(self, fd: int) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([fd], [], [], 0.1)
            if not ready:
                continue
            key = os.read(fd, 1).decode(errors="replace")
            if not key:
                return
            if self._asking.is_set():
                self._keys.put(key)
            elif self.on_key is not None:
                self.on_key(f"key {key!r} pressed")

    def _ask(self, text: str) -> str:
        while not self._keys.empty():
            self._keys.get_nowait()
        self.console.print(text, end=" ")
        self._asking.set()
        try:
            key = self._keys.get()
        finally:
            self._asking.clear()
        self.console.print(repr(key) if key not in "\r\n" else "Enter")
        return key

    def begin(self, joints: Sequence[str]) -> None:
        self.console.print(Text("Hands-free calibration: each joint below moves by itself into both of its mechanical "
                                "stops, slowly where a stop may be, one joint of each arm at a time. Keep the e-stop "
                                "in your hand and the space around both arms clear. Enter moves a pair, any other key "
                                "skips it; a key pressed while a joint moves stops the run at once.",
                                style="bold yellow"))
        self.console.print("Joints, in order: " + ", ".join(joints))

    def confirm(self, joints: Sequence[str]) -> bool:
        them = " and ".join(joints)
        return self._ask(f"{them}: Enter to move {'them' if len(joints) > 1 else 'it'}, any other key to skip:") \
            in "\r\n"

    def watch(self, joint: str) -> None:
        self.console.print(f"Watch {joint}: it turns a little now.")

    def turned_counter_clockwise(self, joint: str, view: npt.NDArray[np.float64], where: str) -> bool | None:
        key = self._ask(f"Looking at {joint} from {where}, did it just turn counter-clockwise? [y/n]").lower()
        return True if key == "y" else False if key == "n" else None


def _apply(args: argparse.Namespace, result: AutoResult) -> dict[str, float]:
    """Write each eRob joint's measured efficiency (plausible ones only) into the hardware file."""
    hardware: HardwareConfig = result.robot.hardware
    values = {}
    for joint in result.asked:
        stiffness = result.outcomes[joint].stiffness
        if joint in hardware.erob_slaves and stiffness is not None and stiffness.family == "erob":
            ratio = stiffness.kp_ratio
            if EFFICIENCY_PLAUSIBLE[0] <= ratio <= EFFICIENCY_PLAUSIBLE[1]:
                values[joint] = round(min(ratio, 1.0), 3)
    if values:
        write_erob_torque_efficiency(args.hardware, values)
    return values


def _report(console: Console, result: AutoResult, output: Path, written: bool, applied: dict[str, float],
            hardware_file: str | None) -> None:
    styles = {"done": "green", "skipped": "yellow", "failed": "bold red", "aborted": "bold red",
              "direction_unknown": "yellow", "not_reached": "dim"}
    if result.aborted:
        console.print(Text(f"stopped: {result.aborted}", style="bold red"))
    console.print(f"wrote {output}" if written else f"{output} was not written: no joint was calibrated")
    for joint in result.asked:
        o = result.outcomes[joint]
        cal = o.calibration
        line = f"  {joint:<22} {o.status:<17}"
        if cal is not None:
            line += f" direction {cal.direction:+d} offset {cal.homing_offset:+.4f} rad"
            if o.flipped:
                line += " (FLIPPED from the prior)"
        line += f"  peak {o.peak_contact_nm:.2f}/{o.cap_nm:.2f} Nm at {o.impact_rad_s:.2f} rad/s  {o.seconds:.1f} s"
        console.print(Text(line, style=styles.get(o.status, "")))
        if o.message:
            console.print(f"      {o.message}")
        for warning in o.warnings:
            console.print(Text(f"      warning: {warning}", style="bold yellow"))
        if o.stiffness is not None:
            s = o.stiffness.as_dict()
            if o.stiffness.family == "erob" and "torque_efficiency" in s:
                console.print(f"      stiffness {s['kp_realised']:.2f} of {s['kp_asked']:.2f} Nm/rad "
                              f"({s['kp_ratio']:.3f}: torque_efficiency {s['torque_efficiency']:.3f}), damping "
                              f"{s['kd_realised']:.3f} of {s['kd_asked']:.3f} Nm*s/rad ({s['kd_ratio']:.3f})")
            elif "kp_divisor" in s:
                console.print(f"      stiffness {s['kp_realised']:.2f} of {s['kp_asked']:.2f} Nm/rad (divisor "
                              f"{s['kp_divisor']:.1f}), damping {s['kd_realised']:.3f} of {s['kd_asked']:.3f} "
                              f"Nm*s/rad (divisor {s['kd_divisor']:.3f})")
        if o.drive_torque_limit:
            console.print(f"      drive torque limit: {o.drive_torque_limit}")
    where = ", ".join(f"{kind} {seconds:.1f} s" for kind, seconds in result.time_by_kind().items() if seconds > 0)
    console.print(f"robot time {result.robot_seconds:.1f} s, wall time {result.wall_seconds:.1f} s; the joints' time "
                  f"went to: {where}")
    if applied:
        console.print(f"wrote the measured torque efficiency of {len(applied)} eRob joints into {hardware_file}")
