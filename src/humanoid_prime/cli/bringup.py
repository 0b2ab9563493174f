"""``prime bringup``: bring Prime up on the real robot (or the virtual one with --emulate) and run it."""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import math
import sys
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import (
    SECONDS,
    add_config_options,
    add_emulation_options,
    add_json_option,
    add_mailbox_option,
    add_realtime_options,
    add_socket_option,
    dds_options,
    member,
    members,
    output_dir,
    output_file,
    real,
    ring_options,
)
from humanoid_prime.cli.addons import Addons, Run, add_addon_options, check_addons
from humanoid_prime.config.controllers import MAX_BRINGUP_RATE_HZ
from humanoid_prime.config.robot import Robot
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_text
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.gain_switch import RENDEZVOUS_S
from humanoid_prime.runtime.run import run_loop
from humanoid_prime.runtime.session import (
    BACKENDS,
    BringupOptions,
    Plan,
    Session,
    claim_control_socket,
    open_session,
    plan_session,
)
from humanoid_prime.runtime.signals import stop_on_signals
from humanoid_prime.runtime.switching import mode_switcher

if TYPE_CHECKING:  # the virtual Prime is imported when a run emulates the robot
    from humanoid_prime.virtual.harness import EmulatorRecord, VirtualPrime
    from humanoid_prime.virtual.load_test import Stiffness


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "bringup", help=summary("bringup"),
        description="Bring Prime up: fold the calibration into the eRob configs, take the EtherCAT ring to OP "
                    "with the fast bring-up loop (SYNC0 derived from update_rate), enable the Sito wrists, start "
                    "the controllers in stages (broadcaster, ZERO_TORQUE, the other modes inactive), then arm "
                    "the eRob gain gate and follow the mode. Keys 1-5 switch modes on a terminal; "
                    "`prime switch MODE` does it from another terminal.")
    p.add_argument("--backends", choices=BACKENDS, default="all",
                   help="all: both buses and the mode controllers; ec / can: that bus alone with only the "
                        "joint-state broadcaster (calibration, diagnostics); default all")
    add_emulation_options(p, "run against the virtual Prime (eRob ring on a veth pair, Sito motors on a CAN bus, "
                             "one MuJoCo plant) inside a private network namespace; needs root or user namespaces")
    add_config_options(p, calibration=True, controllers=True)
    p.add_argument("--interface", metavar="NIC", help="EtherCAT interface (default: from the hardware file)")
    add_mailbox_option(p)
    p.add_argument("--can-interface", metavar="NAME", help="python-can interface (default: from the hardware file)")
    p.add_argument("--can-channel", metavar="NAME", help="python-can channel (default: from the hardware file)")
    p.add_argument("--sync0-period", type=SECONDS, metavar="S",
                   help="cross-check: must equal 1/update_rate (it is derived from it); a different value is "
                        "refused with the reason")
    p.add_argument("--bringup-rate", type=real(above=0.0, at_most=MAX_BRINGUP_RATE_HZ), metavar="HZ",
                   help="EtherCAT bring-up loop rate (default: 1000; at most 2000, the eRob's minimum cycle)")
    add_realtime_options(p, rate_help="control loop rate (default: update_rate of the controllers file; at most "
                                      "2000, the eRob's minimum 500 us cycle); SYNC0 and the bring-up loop follow "
                                      "it, and the Sito wrists while their frames fit the CAN bus (every tick up "
                                      "to about 300 Hz, every 4th at 1 kHz)")
    p.add_argument("--uncalibrated", action="store_true",
                   help="allow STANDBY, LOCOMOTION and REMOTE although the calibration is the identity template "
                        "(refused on the robot otherwise: a pose on wrong offsets drives an arm somewhere nobody "
                        "expects)")
    p.add_argument("--sequential-sdo", action="store_true",
                   help="write the eRob gains one slave after another (the slow baseline) instead of in parallel")
    p.add_argument("--mode", metavar="MODE", help="switch to MODE once up")
    p.add_argument("--sequence", metavar="MODE,...", help="visit these modes, one every --dwell seconds, then stop")
    p.add_argument("--dwell", type=SECONDS, default=2.0, metavar="S", help="seconds per mode of --sequence (default 2)")
    p.add_argument("--duration", type=SECONDS, metavar="S", help="stop after S seconds of control loop")
    p.add_argument("--load-test", nargs="?", const="all", metavar="JOINT,...",
                   help="(with --emulate) measure realised eRob stiffness in STANDBY: push each joint with a known "
                        "torque in the plant and read the deflection; prints nominal vs realised kp")
    p.add_argument("--erob-config-dir", metavar="DIR", type=output_dir,
                   help="keep the folded per-slave eRob configs here")
    add_socket_option(p)
    add_addon_options(p)
    p.add_argument("--summary", metavar="FILE", type=output_file, help="write the run's figures as JSON")
    p.add_argument("--no-live", action="store_true", help="no live table even on a terminal")
    add_json_option(p)
    p.set_defaults(func=run)


def _modes(text: str | None, option: str) -> list[Mode]:
    if text is None:
        return []
    names = [item for item in text.split(",") if item.strip()]
    if not names:
        raise PrimeError(f"{option}: no mode given; name one or more of {', '.join(m.value for m in Mode)}")
    try:
        return [Mode.parse(item) for item in names]
    except ValueError as exc:
        raise PrimeError(f"{option}: {exc}") from None


def options_from_args(args: argparse.Namespace) -> BringupOptions:
    sequence = _modes(args.sequence, "--sequence")
    initial = _modes(args.mode, "--mode")
    if len(initial) > 1:
        raise PrimeError("--mode takes one mode; use --sequence for several")
    if initial and sequence:
        raise PrimeError("--mode (stay in one mode) and --sequence (visit modes, then stop) do not go together; "
                         "give one of them")
    if args.cpu is not None and not args.realtime:
        raise PrimeError("--cpu pins the real-time control thread; it cannot be combined with --no-realtime")
    if (sequence or initial) and args.backends != "all":
        raise PrimeError(f"--backends {args.backends} runs only the joint-state broadcaster; modes need --backends all")
    return BringupOptions(
        backends=args.backends, emulated=args.emulate, hardware_file=args.hardware,
        calibration_file=args.calibration, controllers_file=args.controllers, interface=args.interface,
        can_interface=args.can_interface, can_channel=args.can_channel, sync0_period_s=args.sync0_period,
        bringup_rate=args.bringup_rate, parallel_sdo=False if args.sequential_sdo else None,
        duration=args.duration, mode=initial[0] if initial else None, sequence=sequence, dwell=args.dwell,
        erob_config_dir=args.erob_config_dir, control_socket=args.socket, update_rate=args.rate,
        realtime=args.realtime, cpu=args.cpu, uncalibrated=args.uncalibrated, config=args.config.as_dict(),
        state_folder=args.config.folder.state, ec_mailbox=args.ec_mailbox)


def _load_test_joints(args: argparse.Namespace, robot: Robot) -> list[str]:
    """The eRob joints --load-test names (all of them for a bare --load-test)."""
    if args.load_test == "all":
        return list(robot.hardware.erob_joints)
    joints = [j.strip() for j in args.load_test.split(",") if j.strip()]
    for joint in joints:
        if joint not in robot.hardware.erob_slaves:
            raise PrimeError(f"--load-test: {joint!r} is not an eRob joint "
                             f"(eRob joints: {', '.join(robot.hardware.erob_joints)})")
    return joints


def run(args: argparse.Namespace) -> int:
    options = options_from_args(args)
    ring = ring_options(args, **{"--load-test": args.load_test})
    dds = dds_options(args)
    check_addons(args)
    # Everything is checked before anything opens, and before a private namespace is entered.
    load_test_joints = _load_test_joints(args, plan_session(options).robot) if args.load_test else []
    if options.emulated:
        from humanoid_prime.virtual.harness import enter_private_netns

        enter_private_netns()  # re-executes this command in a private network namespace (returns inside)
    stop = threading.Event()
    report = print if not args.json else (lambda *a, **k: None)
    emulator: EmulatorRecord = {}
    stiffness: list[Stiffness] = []
    addons = Addons()
    with stop_on_signals(stop), contextlib.ExitStack() as stack:
        plan = plan_session(options)
        claim_control_socket(plan, stack)
        virtual = None
        if options.emulated:
            from humanoid_prime.virtual.harness import EMULATOR_STAGE, attach_virtual_prime

            t = time.monotonic()
            virtual = attach_virtual_prime(stack, hardware_file=args.hardware, truth_file=args.truth,
                                           ring_options=ring, record=emulator, avoid_cpu=args.cpu)
            virtual.wire_into(options)
            plan.stage(EMULATOR_STAGE, t)
        with _bringing_up(plan, args):
            session = open_session(plan, stack)
        session.reports.update(load_test=stiffness, emulator=emulator)
        host_graph = None
        if options.emulated:  # the node on the host's graph (as root), the robot in its private namespace
            from humanoid_prime.virtual.harness import host_network

            host_graph = host_network
        # Stamps in the system clock, as ROS 2 nodes on the robot.
        switch = None if session.manager.broadcaster_only else mode_switcher(session.manager, session.impedance)
        addons.attach(Run(session.manager, report=report, epoch_offset=time.time() - time.monotonic(),
                          host_graph=host_graph, switch=switch), args, stack)
        report(f"Prime up in {session.bringup_seconds:.2f} s ({options.backends}"
               f"{', emulated' if options.emulated else ''}):")
        for name, seconds in session.stages:
            report(f"  {name:<28} {seconds * 1e3:9.1f} ms")
        load_test = _start_load_test(session, virtual, load_test_joints, stiffness, stop) \
            if virtual is not None and load_test_joints else None
        if sys.stdout.isatty() and not args.no_live and not args.json:
            from humanoid_prime.cli._live import LiveTable, ModeKeys

            full = not session.manager.broadcaster_only
            if sys.stdin.isatty():
                stack.enter_context(ModeKeys(session.manager.request_mode if full else _refuse, stop.set,
                                             on_reset=session.manager.request_reset))
            graph = (lambda: "DDS control ON") if dds is not None and dds.control else None
            stack.enter_context(LiveTable(session.manager, keys=full, reset_key=sys.stdin.isatty(), status=graph))
        # With --emulate, the plant's true joint angles (rad, joint frame) when the loop ends, beside the measured
        at_end = functools.partial(_record_joints, emulator, virtual) if virtual is not None else None
        run_loop(session, stop, report=lambda line: print(line, file=sys.stderr if args.json else sys.stdout),
                 at_end=at_end)
        if load_test is not None:
            load_test.join(timeout=30.0)
    session.reports.update(addons.summaries())
    summary = session.summary()
    if args.summary:
        atomic_write_text(Path(args.summary), json.dumps(summary, indent=2) + "\n")
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        _print_report(summary)
    problems = summary["problems"]  # the run's own lines, as the summary gives them
    if isinstance(problems, list) and problems:
        more = f" (and {len(problems) - 1} more, listed above)" if len(problems) > 1 else ""
        print(f"prime bringup: FAULTED: {problems[0]}{more}", file=sys.stderr)
        return 1
    return 0


@contextlib.contextmanager
def _bringing_up(plan: Plan, args: argparse.Namespace) -> Iterator[None]:
    """A live status on a terminal while the buses come up (the slow part on the real robot)."""
    if args.json or not sys.stdout.isatty():
        yield
        return
    from humanoid_prime.cli._common import console
    from humanoid_prime.cli._live import Working

    with Working(console(), "bringing Prime up: EtherCAT ring to OP, wrists, controllers") as working:
        plan.on_stage = lambda name: working.update(f"bringing Prime up: {name} done")
        try:
            yield
        finally:
            plan.on_stage = None


def _refuse(mode: Mode) -> None:
    """Mode keys in a broadcaster-only run: nothing to switch."""


def _record_joints(record: EmulatorRecord, virtual: VirtualPrime) -> None:
    record["joints"] = virtual.control.joints()


def _start_load_test(session: Session, virtual: VirtualPrime, joints: list[str], results: list[Stiffness],
                     stop: threading.Event) -> threading.Thread:
    from humanoid_prime.virtual.load_test import measure_stiffness

    def work() -> None:
        try:
            session.manager.request_mode(Mode.STANDBY)
            time.sleep(session.config.standby.duration + 1.0)
            results.extend(measure_stiffness(session, virtual.control, joints, stop=stop))
        except PrimeError as exc:
            session.record_fault("load_test", str(exc))
        finally:
            stop.set()

    thread = threading.Thread(target=work, name="load-test", daemon=True)
    thread.start()
    return thread


def _print_report(summary: Mapping[str, object]) -> None:
    """The run's summary (``Session.summary``, as JSON has it) for a person."""
    ethercat = member(summary, "ethercat_bringup")
    if "mailbox" in ethercat:
        drops = member(ethercat, "mailbox_drops")
        print(f"EtherCAT mailboxes: {ethercat['mailbox']}" + (
            f"; messages dropped: {drops['late']} late, {drops['other object']} for another object, "
            f"{drops['unrecognised']} unrecognised, {drops['malformed']} malformed" if drops else ""))
    for switch in members(summary["mode_switches"]):
        state = "ok" if switch["ok"] else f"FAILED {switch['failed']}"
        if not switch["together"]:
            state += f" (a slave came late; the others made their last write after {RENDEZVOUS_S * 1e3:.0f} ms)"
        print(f"mode {switch['mode']:<12} gains on all slaves in {_ms(switch['wall_seconds']):6.1f} ms, "
              f"skew {_ms(switch['skew_seconds']):5.1f} ms, retries {switch['retries']}: {state}")
    tick, jitter = member(summary, "tick_us"), member(summary, "jitter_us")
    cpu, io = member(summary, "tick_cpu_us"), member(summary, "tick_io_us")
    if summary["ticks"]:
        print(f"loop: {summary['ticks']} ticks at {summary['update_rate']:g} Hz, "
              f"tick median {tick['median']:.0f} us p99 {tick['p99']:.0f} us (our CPU {cpu['median']:.0f} / "
              f"{cpu['p99']:.0f} us, bus I/O {io['median']:.0f} / {io['p99']:.0f} us), "
              f"period jitter p99 {jitter['p99']:.0f} us, overruns {summary['overruns']}")
    for row in members(summary["load_test"]):
        print(f"load test {row['joint']:<22} kp nominal {row['kp_nominal']:5.1f}  realised {row['kp_realised']:5.1f} "
              f"Nm/rad  ({row['ratio']:.2f}x, torque_efficiency {row['torque_efficiency']:g})")
    for fault in members(summary["faults"]):
        until = "held to the end" if fault["until_s"] is None else f"until {fault['until_s']:.2f} s"
        print(f"{fault['level']:<5} {fault['key']} at {fault['since_s']:.2f} s ({until}): {fault['text']}")
    end = member(summary, "end")
    if "slaves" in end:
        print(f"at the end: {end['slaves_op']} of {end['slaves']} EtherCAT slaves in OP, "
              f"{end['drives_enabled']} drives enabled, in fault: {_names(end['drives_faulted']) or 'none'}")
    if "sito" in end:
        print(f"at the end: {end['sito_online']} of {end['sito']} Sito wrists answering")


def _ms(seconds: object) -> float:
    return float(seconds) * 1e3 if isinstance(seconds, (int, float)) else math.nan


def _names(value: object) -> str:
    return ", ".join(str(name) for name in value) if isinstance(value, list) else ""
