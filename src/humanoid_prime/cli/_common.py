"""Options and output helpers shared by the subcommands. Every command imports this module, so it imports only
what building a parser needs; the rest (rich, the file helpers) is imported where it is used."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from humanoid_prime.dds.domain import MAX_DOMAIN_ID, Discovery
from humanoid_prime.errors import PrimeError
from humanoid_prime.record.topics import TOPICS as RECORD_TOPICS
from humanoid_prime.runtime.socket import default_socket_path

if TYPE_CHECKING:
    from rich.console import Console

CONFIG_RULE = ("default: the robot's config folder ($PRIME_CONFIG_DIR, else ~/.config/prime, with a --robot "
               "subfolder), else the bundled template; `prime config show` tells which")


def add_config_options(parser: argparse.ArgumentParser, *, calibration: bool = False,
                       controllers: bool = False) -> None:
    """--robot and the configuration files a command reads; ``main`` resolves them by one rule for every
    command (``config.location``) before the command runs, so ``args.hardware`` etc. are always paths."""
    parser.add_argument("--robot", metavar="NAME",
                        help="the robot's config subfolder, for labs with several Primes (default: $PRIME_ROBOT)")
    parser.add_argument("--hardware", metavar="FILE", help=f"hardware file ({CONFIG_RULE})")
    if calibration:
        parser.add_argument("--calibration", metavar="FILE", help=f"calibration file ({CONFIG_RULE})")
    if controllers:
        parser.add_argument("--controllers", metavar="FILE", help=f"controllers file ({CONFIG_RULE})")


def resolve_config(args: argparse.Namespace) -> None:
    """Resolve the configuration files of a command that takes ``--robot`` (``add_config_options``):
    ``args.config`` holds the three files with where each came from, and ``args.hardware``,
    ``args.calibration`` and ``args.controllers`` become their paths."""
    from humanoid_prime.config.location import resolve_all

    files = resolve_all(args.robot, hardware=getattr(args, "hardware", None),
                        calibration=getattr(args, "calibration", None),
                        controllers=getattr(args, "controllers", None))
    args.config = files
    args.hardware, args.calibration, args.controllers = (str(c.path) for c in files)


def add_socket_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--socket", metavar="PATH", help=f"control socket (default: {default_socket_path()})")


def add_domain_option(parser: argparse.ArgumentParser, *, with_dds: bool = True) -> None:
    parser.add_argument("--domain", type=whole(at_least=0, at_most=MAX_DOMAIN_ID), metavar="N",
                        help=f"{'(with --dds) ' if with_dds else ''}ROS 2 domain id (default: ROS_DOMAIN_ID, else 0)")


def add_dds_options(parser: argparse.ArgumentParser, dds_help: str | None = None, *, node: bool = False) -> None:
    """``--dds`` and ``--domain``; with ``node`` (a run that is Prime on the graph) also ``--dds-control`` and
    ``--namespace``."""
    parser.add_argument("--dds", action="store_true",
                        help=dds_help or "be node 'prime' on the ROS 2 graph over DDS: publish /prime/joint_states, "
                                         "/control_mode, /safety_status, /diagnostics, /robot_description, /tf "
                                         "(and /clock in simulation); nothing on the graph can move the robot "
                                         "unless --dds-control is given too")
    if node:
        parser.add_argument("--dds-control", action="store_true",
                            help="(with --dds) take mode requests (/prime/mode_request) and REMOTE commands from "
                                 "the ROS 2 graph: any participant in the domain that discovery reaches can then "
                                 "move the robot (ROS_AUTOMATIC_DISCOVERY_RANGE and ROS_STATIC_PEERS limit who)")
        parser.add_argument("--namespace", metavar="NAME",
                            help="(with --dds) ROS 2 namespace of the node and every topic, so several Primes share "
                                 "one domain (default: none)")
        parser.add_argument("--ros-backend", choices=ROS_BACKENDS, default=None,
                            help="(with --dds) rclpy: an rclpy node on the middleware ROS 2 is set to, with "
                                 "parameters, /rosout, services and trajectory actions; dds: one bare Cyclone DDS "
                                 "participant (topics only) (default: rclpy where it can be imported, else dds)")
    add_domain_option(parser)


@dataclass(frozen=True)
class DdsOptions:
    """Where and how a run is on the ROS 2 graph, checked before anything starts."""

    domain: int
    namespace: str
    control: bool
    discovery: Discovery
    backend: str = "dds"
    backend_asked: bool = False  # --ros-backend given (else chosen by what can be imported)

    def describe(self) -> str:
        node = "/prime" if self.namespace == "/" else f"{self.namespace}/prime"
        control = "control from the graph ON" if self.control else "publishing only (no --dds-control)"
        how = f"{self.discovery.describe()}" if self.backend == "dds" else "rclpy"
        return f"ROS 2 domain {self.domain}, node {node}, {how}; {control}"


def dds_options(args: argparse.Namespace) -> DdsOptions | None:
    """The run's DDS options when ``--dds`` was given, None for no DDS; every option and ROS 2 variable is
    checked here, before anything starts."""
    from humanoid_prime.dds.domain import discovery, domain_id, node_namespace

    control, namespace = getattr(args, "dds_control", False), getattr(args, "namespace", None)
    backend = getattr(args, "ros_backend", None)
    if not args.dds:
        given = [name for name, value in (("--domain", args.domain), ("--dds-control", control),
                                          ("--namespace", namespace), ("--ros-backend", backend))
                 if value not in (None, False)]
        if given:
            raise PrimeError(f"{', '.join(given)} needs --dds")
        return None
    return DdsOptions(domain_id(args.domain), node_namespace(namespace), control, discovery(),
                      ros_backend(backend), backend is not None)


ROS_BACKENDS = ("rclpy", "dds")


def ros_backend(asked: str | None) -> str:
    """The node's backend: ``asked`` (``--ros-backend``), else rclpy where it can be imported (a sourced ROS 2
    install, or the wheels of ``pip install 'humanoid-prime[ros-jazzy]'``), else bare Cyclone DDS."""
    import importlib.util

    found = importlib.util.find_spec("rclpy") is not None
    if asked == "rclpy" and not found:
        raise PrimeError("--ros-backend rclpy: rclpy cannot be imported here; source a ROS 2 install (source "
                         "/opt/ros/jazzy/setup.bash) or install the wheels (pip install 'humanoid-prime[ros-jazzy]')")
    return asked or ("rclpy" if found else "dds")


def dds_domain(args: argparse.Namespace) -> int | None:
    """The run's DDS domain when ``--dds`` was given, None for no DDS; checked before anything starts."""
    options = dds_options(args)
    return None if options is None else options.domain


def mcap_file(text: str) -> Path:
    """argparse type of a recording: an .mcap file that can be written."""
    if not text.endswith(".mcap"):
        raise argparse.ArgumentTypeError(f"a recording is an .mcap file, got {text!r}")
    return output_file(text)


def add_record_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--record", metavar="FILE.mcap", type=mcap_file,
                        help="record every topic of the run to FILE.mcap (ROS 2 messages: ros2 bag play, Foxglove, "
                             "rosbags and `prime plot` read it)")
    parser.add_argument("--topics", type=record_topics, metavar="TOPIC,...",
                        help="(with --record) record only these topics, to keep a recording small (default: all of "
                             f"{', '.join(RECORD_TOPICS)})")



def record_topics(text: str) -> tuple[str, ...]:
    """argparse type of ``--topics``: comma-separated topic names, each one a recording can hold."""
    chosen = tuple(dict.fromkeys("/" + name.strip().strip("/") for name in text.split(",") if name.strip()))
    unknown = [name for name in chosen if name not in RECORD_TOPICS]
    if unknown or not chosen:
        raise argparse.ArgumentTypeError(f"{', '.join(unknown) or 'no topic'}: a recording can hold "
                                         f"{', '.join(RECORD_TOPICS)}")
    return chosen


DEFAULT_WEB_PORT = 8080


def add_web_option(parser: argparse.ArgumentParser) -> None:
    """``--web`` serves the live view, on ``--port`` (``--web PORT``, the old spelling, still works);
    ``resolve_web`` leaves the port to serve on in ``args.web`` (None: no view)."""
    port = whole(at_least=0, at_most=65535)
    parser.add_argument("--web", nargs="?", const=True, type=port, metavar="PORT",
                        help="serve the live 3D view on http://127.0.0.1:PORT/ (PORT: --port)")
    parser.add_argument("--port", dest="web_port", type=port, metavar="PORT",
                        help=f"(with --web) the view's port (default {DEFAULT_WEB_PORT}; the next free port if "
                             "taken; 0: any)")


def resolve_web(args: argparse.Namespace) -> None:
    """``args.web``: the port the view serves on, or None without ``--web``."""
    if args.web is None:
        if args.web_port is not None:
            raise PrimeError("--port is the port of the view: give --web too")
        return
    if args.web_port is not None:
        args.web = args.web_port
    elif args.web is True:
        args.web = DEFAULT_WEB_PORT


def check_web(args: argparse.Namespace) -> None:
    """``--web`` serves on this machine's loopback; an emulated run lives in a private network namespace that
    a browser cannot reach, so it is refused with the way that works (``prime view`` over the control socket)."""
    if args.web is not None and args.emulate:
        raise PrimeError("--web cannot serve an emulated run: it runs in a private network namespace your browser "
                         f"cannot reach; run `prime view --socket {args.socket or default_socket_path()}` beside it")


def add_emulation_options(parser: argparse.ArgumentParser, emulate_help: str) -> None:
    """``--emulate`` and the virtual Prime's tunables (``ring_options`` reads them back)."""
    parser.add_argument("--emulate", action="store_true", help=emulate_help)
    parser.add_argument("--truth", metavar="FILE",
                        help="(with --emulate) the virtual robot's wiring and factory offsets, as a calibration file")
    parser.add_argument("--dc-lock-cycles", type=whole(at_least=0, at_most=1_000_000), metavar="N",
                        help="(with --emulate) DC lock cycles per drive")
    parser.add_argument("--mailbox-latency", type=real(at_least=0.0, below=1.0), metavar="S",
                        help="(with --emulate) time each emulated drive takes to answer an SDO (default 0.0005)")
    parser.add_argument("--gain-bytes", type=int, choices=(2, 4),
                        help="(with --emulate) size of the emulated eRob's loop-gain objects: 2 as ZeroErr's EDS "
                             "declares them (default), 4 as one public host reads them")
    parser.add_argument("--rated-torque", type=real(above=0.0, at_most=1000.0), metavar="NM",
                        help="(with --emulate) what the emulated eRob report in 0x6076 (default 23, the nominal "
                             "eRob70 figure; an eRob80H120I reports 31)")
    parser.add_argument("--quirks", metavar="NAME,...",
                        help="(with --emulate) the emulated eRob behave as some real slaves do: "
                             "reserved-bits, counter, no-size, normal-upload, slow-sii, slow-states, emergency, "
                             "abort-service, or all (docs/hardware.md)")


def ring_options(args: argparse.Namespace, **more: object) -> dict[str, Any]:
    """The emulator tunables given on the command line; any of them, or a truthy ``more`` option (named as on
    the command line), without --emulate is an error."""
    given = {"--truth": args.truth, "--dc-lock-cycles": args.dc_lock_cycles,
             "--mailbox-latency": args.mailbox_latency, "--gain-bytes": args.gain_bytes,
             "--rated-torque": args.rated_torque, "--quirks": args.quirks, **more}
    used = [name for name, value in given.items() if value is not None and value is not False]
    if used and not args.emulate:
        raise PrimeError(f"{', '.join(used)}: only with --emulate (these act on the virtual Prime)")
    if args.truth is not None:  # read by the emulator once it runs: checked now, before anything starts
        from humanoid_prime.config.calibration import load_calibration
        from humanoid_prime.config.hardware import load_hardware

        load_calibration(load_hardware(args.hardware), args.truth)
    options: dict[str, Any] = {}
    if args.dc_lock_cycles is not None:
        options["dc_lock_cycles"] = args.dc_lock_cycles
    if args.mailbox_latency is not None:
        options["mailbox_latency_s"] = args.mailbox_latency
    if args.gain_bytes is not None:
        options["gain_bytes"] = args.gain_bytes
    if args.rated_torque is not None:
        options["rated_torque_mnm"] = round(args.rated_torque * 1000)
    if args.quirks is not None:
        from humanoid_prime.virtual.ring.quirks import Quirks

        try:
            Quirks.parse(args.quirks)
        except ValueError as exc:
            raise PrimeError(f"--quirks: {exc}") from None
        options["quirks"] = args.quirks
    return options


def add_mailbox_option(parser: argparse.ArgumentParser) -> None:
    """--ec-mailbox: who works the eRob's mailboxes, overriding ``buses.ethercat.mailbox``."""
    parser.add_argument("--ec-mailbox", choices=("prime", "soem"),
                        help="who works the eRob's mailboxes (SDO): prime, Prime's CoE layer, or soem, SOEM alone as "
                             "before that layer (default: buses.ethercat.mailbox in prime_hardware.yaml, else prime)")


def add_realtime_options(parser: argparse.ArgumentParser, *, rate_help: str | None) -> None:
    """--rate (unless ``rate_help`` is None), --cpu and --no-realtime: the loop's rate and how it holds its
    period on a busy machine."""
    from humanoid_prime.config.controllers import MAX_BRINGUP_RATE_HZ

    if rate_help is not None:
        parser.add_argument("--rate", type=real(above=0.0, at_most=MAX_BRINGUP_RATE_HZ), metavar="HZ",
                            help=rate_help)
    parser.add_argument("--cpu", type=cpu_number, metavar="N",
                        help="pin the control loop to CPU N, with the process's other threads, which share its "
                             "interpreter lock (with --emulate, the emulated robot runs off it)")
    parser.add_argument("--no-realtime", dest="realtime", action="store_false",
                        help="leave the control thread at normal priority, its memory unlocked and the garbage "
                             "collector automatic (default: real-time scheduling and locked memory where allowed, "
                             "the GC frozen after start-up and run only between ticks)")


def cpu_number(text: str) -> int:
    """argparse type of a CPU this process may run on."""
    from humanoid_prime.runtime.realtime import check_cpu

    value = whole(at_least=0)(text)
    try:
        check_cpu(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return value


def real(*, above: float | None = None, at_least: float | None = None, at_most: float | None = None,
         below: float | None = None) -> Callable[[str], float]:
    """argparse type of a finite number within bounds; a bad value is one line naming the option."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text} is not a finite number")
        for bound, holds, words in ((above, lambda b: value > b, "above"), (at_least, lambda b: value >= b, "at least"),
                                    (at_most, lambda b: value <= b, "at most"), (below, lambda b: value < b, "below")):
            if bound is not None and not holds(bound):
                raise argparse.ArgumentTypeError(f"must be {words} {bound:g}, got {text}")
        return value
    return parse


def whole(*, at_least: int | None = None, at_most: int | None = None) -> Callable[[str], int]:
    """argparse type of an integer within bounds (decimal or 0x hex)."""
    def parse(text: str) -> int:
        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if (at_least is not None and value < at_least) or (at_most is not None and value > at_most):
            span = f"{at_least if at_least is not None else '...'}..{at_most if at_most is not None else ''}"
            raise argparse.ArgumentTypeError(f"must be in {span}, got {text}")
        return value
    return parse


# The longest duration an option takes: a year. Longer is a slip of the keyboard, and would overflow the clocks
# and sleeps it reaches (their limit is near 9.2e9 s).
LONGEST_S = 366 * 24 * 3600.0
SECONDS = real(above=0.0, at_most=LONGEST_S)  # a duration that must pass
SECONDS_OR_ZERO = real(at_least=0.0, at_most=LONGEST_S)


def add_duration_option(parser: argparse.ArgumentParser, help_text: str, *, default: float | None = None,
                        zero: bool = False) -> None:
    """``--duration S`` (``--seconds``, its old spelling, still works for one release)."""
    kind = SECONDS_OR_ZERO if zero else SECONDS
    parser.add_argument("--duration", type=kind, default=default, metavar="S", help=help_text)
    add_hidden_alias(parser, "--seconds", "duration", type=kind)


def add_hidden_alias(parser: argparse.ArgumentParser, option: str, dest: str, **kwargs: Any) -> None:
    """An old spelling of an option, kept working for one release and left out of --help."""
    parser.add_argument(option, dest=dest, default=argparse.SUPPRESS, help=argparse.SUPPRESS, **kwargs)


def output_file(text: str) -> Path:
    """argparse type of an output file: refused at once if it could not be written at the end of the run."""
    from humanoid_prime.files import output_problem

    problem = output_problem(text)
    if problem is not None:
        raise argparse.ArgumentTypeError(f"cannot write there: {problem}")
    return Path(text).expanduser()


def output_dir(text: str) -> Path:
    """argparse type of an output folder, checked like ``output_file``."""
    from humanoid_prime.files import output_problem

    problem = output_problem(text, directory=True)
    if problem is not None:
        raise argparse.ArgumentTypeError(f"cannot write there: {problem}")
    return Path(text).expanduser()


OUTPUT_TYPES = (output_file, output_dir, mcap_file)
# What a command reads from a path, besides the configuration files: an output must never be one of them.
INPUT_OPTIONS = {"hardware": "--hardware", "calibration": "--calibration", "controllers": "--controllers",
                 "truth": "--truth", "prior": "--prior", "recording": "the recording", "model": "--model",
                 "file": "the file checked"}


def chosen_actions(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[argparse.Action]:
    """The arguments of the (sub)command ``args`` was parsed for, the parsers on its way included."""
    actions: list[argparse.Action] = []
    while parser is not None:
        actions += parser._actions
        subparsers = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        parser = subparsers.choices.get(getattr(args, subparsers.dest, None)) if subparsers is not None else None
    return actions


def check_outputs(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse, before anything starts, an output path that is one of the command's inputs or another of its
    outputs: writing it would destroy what the run reads, or what it wrote a moment before. A command may allow
    a pair (``args.may_overwrite``: (output dest, input dest)), e.g. calibrate writing the calibration it refines."""
    allowed = getattr(args, "may_overwrite", ())
    outputs = {action.dest: "/".join(action.option_strings) or action.metavar for action in
               chosen_actions(parser, args) if action.type in OUTPUT_TYPES
               and action.help != argparse.SUPPRESS and getattr(args, action.dest, None)}  # an old spelling: once
    seen: dict[Path, str] = {}
    for dest, option in outputs.items():
        path = Path(getattr(args, dest)).expanduser().absolute().resolve()
        if path in seen:
            raise PrimeError(f"{option} and {seen[path]} name one file ({path}): each output needs its own")
        seen[path] = option
        for source, source_option in INPUT_OPTIONS.items():
            given = getattr(args, source, None)
            if not isinstance(given, (str, Path)) or (dest, source) in allowed:
                continue
            if Path(given).expanduser().absolute().resolve() == path:
                raise PrimeError(f"{option} {getattr(args, dest)} is also {source_option}, which this command "
                                 "reads; writing it would destroy it: name another file")


def console(*, stderr: bool = False) -> Console:
    """A rich console; piped or redirected, wide enough that tables and reports are never wrapped."""
    from rich.console import Console

    out = Console(stderr=stderr)
    return out if out.is_terminal else Console(stderr=stderr, width=200)


def write_summary(args: argparse.Namespace, summary: Any) -> None:
    """``--summary FILE``: the run's figures as JSON, written atomically (nothing without the option)."""
    if getattr(args, "summary", None):
        from humanoid_prime.files import atomic_write_text

        atomic_write_text(args.summary, json.dumps(summary, indent=2) + "\n")


def add_json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON")


def print_json(data: Any) -> None:
    json.dump(data, sys.stdout, indent=2)
    sys.stdout.write("\n")
