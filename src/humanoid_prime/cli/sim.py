"""``prime sim``: the simulated Prime (MuJoCo), brought up with the staged start and run through the
demonstration (every mode in 20 simulated seconds), or held in one mode. ``--hil can`` puts the Sito
wrists behind real CAN frames: SitoSystem and emulated motors on a virtual bus (``virtual/hil.py``)."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable
from itertools import groupby
from typing import Any

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import (
    SECONDS,
    DdsOptions,
    add_config_options,
    add_json_option,
    dds_options,
    output_file,
    print_json,
)
from humanoid_prime.cli._live import LiveTable, ModeKeys, ProgressLines
from humanoid_prime.cli.addons import Addons, Run, add_addon_options, check_addons
from humanoid_prime.config.controllers import ControllersConfig, check_command_limits, load_controllers
from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.drivers.erob.gains import check_erob_limits, check_mode_gains
from humanoid_prime.drivers.mujoco.system import MujocoSystem
from humanoid_prime.drivers.sito.system import check_wire_limits
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_text
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.socket import ControlServer, default_socket_path
from humanoid_prime.runtime.switching import mode_switcher
from humanoid_prime.sim.demo import DEMO_SECONDS, SCHEDULE, START_POSE, Simulation, Step, build_simulation, demo_stream
from humanoid_prime.virtual.hil import build_hil_simulation

VIEWER_SYNC_S = 1.0 / 60.0
VIEWER_CLOSE_S = 5.0
HIL_CHOICES = ("none", "can")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "sim", help=summary("sim"),
        description="Bring up the simulated Prime (MuJoCo, MIT law at the physics rate) with the staged start and "
                    f"run the {DEMO_SECONDS:g} s demonstration: ZERO_TORQUE, DAMPING, STANDBY, LOCOMOTION, REMOTE "
                    "(a scripted command stream; with --dds-control, commands from the ROS 2 graph), DAMPING. On a "
                    "terminal, keys 1-5 switch modes and q quits.")
    p.add_argument("--duration", type=SECONDS, metavar="S",
                   help=f"simulated seconds to run (default: {DEMO_SECONDS:g}; with --mode, until q or Ctrl-C)")
    p.add_argument("--fast", action="store_true", help="run as fast as possible instead of in real time")
    p.add_argument("--viewer", action="store_true", help="show the MuJoCo viewer (needs a display)")
    p.add_argument("--mode", metavar="MODE", help="stay in MODE instead of running the demonstration")
    p.add_argument("--summary", metavar="FILE", type=output_file, help="write a JSON summary of the run to FILE")
    p.add_argument("--model", metavar="FILE", help="MuJoCo model (default: the bundled prime.xml)")
    p.add_argument("--hil", choices=HIL_CHOICES, default="none",
                   help="hardware in the loop: 'can' drives the Sito wrists through SitoSystem and emulated motors "
                        "on a virtual CAN bus, their plants the wrists of the same model (default: none)")
    p.add_argument("--socket", metavar="PATH",
                   help=f"control socket for 'prime switch' (default: {default_socket_path()})")
    add_addon_options(p)
    add_config_options(p, controllers=True)
    add_json_option(p)
    p.set_defaults(func=run)


def _open_viewer(system: MujocoSystem) -> tuple[Any, Callable[[], None]]:
    """The passive MuJoCo viewer on ``system`` and the function that closes it."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise PrimeError("--viewer needs a display but neither DISPLAY nor WAYLAND_DISPLAY is set; "
                         "run without --viewer for a headless simulation")
    try:
        import glfw
        import mujoco.viewer

        # The viewer exits the process when GLFW cannot start, so try GLFW here first.
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            started = glfw.init()
        if not started:
            reason = str(caught[-1].message) if caught else "GLFW could not start"
            raise PrimeError(f"cannot open the MuJoCo viewer: {reason}")
        glfw.terminate()
        before = set(threading.enumerate())
        viewer = mujoco.viewer.launch_passive(system.model, system.data, show_left_ui=False, show_right_ui=False)
        viewer_threads = set(threading.enumerate()) - before
    except PrimeError:
        raise
    except Exception as exc:  # GL, display or platform problems, with the library's own text
        raise PrimeError(f"cannot open the MuJoCo viewer: {str(exc).strip() or type(exc).__name__}") from None

    def close() -> None:
        # The window must be gone before the interpreter exits, or GL teardown races it.
        viewer.close()
        for thread in viewer_threads:
            thread.join(timeout=VIEWER_CLOSE_S)

    return viewer, close


def _viewer_sync(viewer: Any, stop: threading.Event) -> Callable[[], None]:
    """A per-tick hook that redraws the viewer at about 60 Hz and stops the run when its window closes."""
    last = -math.inf

    def sync() -> None:
        nonlocal last
        wall = time.perf_counter()
        if wall - last >= VIEWER_SYNC_S:
            last = wall
            if not viewer.is_running():
                stop.set()
            viewer.sync()

    return sync


def _visits(modes: list[str]) -> str:
    """``A -> B x2 -> C``: a mode entered again while active (a repeated request) counts, it does not repeat."""
    return " -> ".join(mode if (n := len(list(run))) == 1 else f"{mode} x{n}" for mode, run in groupby(modes))


def _format_line(summary: dict[str, Any]) -> str:
    median, p99 = summary["tick_us"]["median"], summary["tick_us"]["p99"]
    rtf = summary["realtime_factor"]
    tick = f"tick {median:.0f}/{p99:.0f} us median/p99" if median is not None else "no ticks"
    return (f"visited {_visits(summary['modes_visited'])} | {summary['ticks']} ticks, "
            f"{summary['sim_seconds']:.2f} s simulated in {summary['wall_seconds']:.2f} s"
            f"{f' ({rtf:.1f}x real time)' if rtf else ''} | {tick} | {len(summary['fallbacks'])} fallbacks"
            f" | {summary['refused']['count']} commands refused by the body check"
            + (f" | recorded {summary['record']['messages'].get('/prime/joint_states', 0)} ticks, "
               f"{summary['record']['dropped_ticks']} DROPPED" if summary.get("record", {}).get("dropped_ticks")
               else "")
            + (f" | CAN {summary['can']['host_frames_sent']} frames sent, {summary['can']['host_frames_received']} "
               "received" if "can" in summary else ""))


@contextlib.contextmanager
def _sigterm_stops() -> Any:
    """SIGTERM stops the run like Ctrl-C, so every cleanup (terminal, hardware) runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def run(args: argparse.Namespace) -> int:
    try:
        mode = Mode.parse(args.mode) if args.mode is not None else None
    except ValueError as exc:
        raise PrimeError(str(exc)) from None
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise PrimeError(f"--duration must be a positive number of seconds, got {args.duration:g}")
    duration = args.duration if args.duration is not None else (None if mode is not None else DEMO_SECONDS)
    dds = dds_options(args)
    check_addons(args)

    robot = load_robot(args.hardware, use_sim=True)
    config = load_controllers(robot.names, args.controllers)
    check_mode_gains(config, robot.hardware)  # a configuration tried in simulation must run on the robot
    check_command_limits(config, robot)
    check_erob_limits(robot.hardware)
    check_wire_limits(robot)
    # The control socket is claimed before anything starts: a second instance, or a path that is not free,
    # stops here with the reason.
    server = ControlServer(path=args.socket).start()
    try:
        return _run(args, robot, config, mode, duration, dds, server)
    finally:
        server.close()


def _run(args: argparse.Namespace, robot: Robot, config: ControllersConfig, mode: Mode | None,
         duration: float | None, dds: DdsOptions | None,
         server: ControlServer) -> int:
    hil = None
    if args.hil == "can":
        hil = build_hil_simulation(robot, config, initial_pose=START_POSE, model_path=args.model)
        system, manager, start, close = hil.system, hil.manager, hil.start, hil.close
    else:
        system, manager = build_simulation(robot, config, initial_pose=START_POSE, model_path=args.model)
        start, close = (lambda: manager.start(now=system.sim_time)), manager.shutdown
    manager.configuration = {kind: entry for kind, entry in args.config.as_dict().items() if kind != "calibration"}
    try:
        # With --dds-control, REMOTE follows the graph (prime remote, a policy node), not the scripted stream.
        stream = None if dds is not None and dds.control else demo_stream(robot, config, manager)
        viewer, close_viewer = _open_viewer(system) if args.viewer else (None, None)
    except BaseException:
        close()  # the CAN buses are open already
        raise
    schedule = SCHEDULE if mode is None else (Step(0.0, mode),)
    sim = Simulation(system, manager, schedule=schedule, stream=stream, realtime=not args.fast,
                     lock=viewer.lock if viewer is not None else None)
    stop = threading.Event()
    out = sys.stderr if args.json else sys.stdout
    live_terminal = out.isatty() and not args.json

    def status() -> str:
        wall = sim.wall_elapsed()
        rate = f"{system.sim_time / wall:5.1f}x real time" if wall > 0 else ""
        driver = "demonstration" if mode is None and sim.following_schedule else "operator"
        wrists = ", wrists over CAN" if hil is not None else ""
        graph = ", DDS control ON" if dds is not None and dds.control else ""
        return f"sim {system.sim_time:6.2f} s  wall {wall:6.2f} s  {rate}  ({driver}{wrists}{graph})"

    table = LiveTable(manager, status=status) if live_terminal else None

    def operator_mode(requested: Mode) -> None:
        sim.take_over()
        manager.request_mode(requested)
        if table is not None:
            table.note = f"operator: {requested.value}"

    hooks: list[Callable[[], None]] = []
    if table is None:
        hooks.append(ProgressLines(manager, stream=out, clock=lambda: sim.now).poll)
    if viewer is not None:
        hooks.append(_viewer_sync(viewer, stop))

    def on_tick() -> None:
        for hook in hooks:
            hook()

    addons = Addons()
    with contextlib.ExitStack() as stack, _sigterm_stops():
        if close_viewer is not None:
            stack.callback(close_viewer)
        stack.callback(close)
        try:
            start()
            stages = " -> ".join(name for name, _ in manager.stages)
            print(f"staged start: {stages} ({sum(s for _, s in manager.stages) * 1e3:.1f} ms); "
                  f"ZERO_TORQUE active, the other mode controllers loaded inactive", file=out, flush=True)
            from humanoid_prime.view.feeds import manager_source

            state, _ = manager_source(manager)  # for the run's whole life: no detach
            switch = mode_switcher(manager, before=sim.take_over)
            server.attach(switch_mode=switch, state=state)
            # Stamps in simulated time, published on /clock; --fast has no deadline, so a writer makes the loop
            # wait instead of dropping a tick.
            run = Run(manager, report=lambda line: print(line, file=out, flush=True),
                      request_mode=lambda text: operator_mode(Mode.parse(text)), switch=switch, sim_clock=True,
                      wait=args.fast,
                      title="Prime (simulated)", state=state)
            addons.attach(run, args, stack)
            keys = stack.enter_context(ModeKeys(operator_mode, stop.set))
            if table is not None:
                table.keys = keys.active
                stack.enter_context(table)
            sim.run(duration, stop=stop, on_tick=on_tick if hooks else None)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM before the loop began
            sim.stopped_by = "interrupt"
        summary = sim.summary()
    summary["hil"] = args.hil
    summary.update(addons.summaries())
    if hil is not None:
        summary["can"] = hil.frame_counts()  # after shutdown: the disable frames count too

    if args.summary:
        atomic_write_text(args.summary, json.dumps(summary, indent=2) + "\n")
    if args.json:
        print_json(summary)
    else:
        print(_format_line(summary), flush=True)
    if mode is None and sim.following_schedule and summary["fallbacks"]:
        first = summary["fallbacks"][0]
        print(f"prime sim: {len(summary['fallbacks'])} fallbacks during the demonstration; first at tick "
              f"{first['tick']}: {first['reason']}", file=sys.stderr)
        return 1
    return 0
