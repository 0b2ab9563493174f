"""Options and output helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from humanoid_prime.errors import PrimeError
from humanoid_prime.files import output_problem
from humanoid_prime.runtime.socket import default_socket_path


def add_config_options(parser: argparse.ArgumentParser, *, calibration: bool = False,
                       controllers: bool = False) -> None:
    parser.add_argument("--hardware", metavar="FILE", help="hardware file (default: bundled prime_hardware.yaml)")
    if calibration:
        parser.add_argument("--calibration", metavar="FILE",
                            help="calibration file (default: bundled prime_calibration.yaml)")
    if controllers:
        parser.add_argument("--controllers", metavar="FILE",
                            help="controllers file (default: bundled prime_controllers.yaml)")


def add_socket_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--socket", metavar="PATH", help=f"control socket (default: {default_socket_path()})")


def add_emulation_options(parser: argparse.ArgumentParser, emulate_help: str) -> None:
    """``--emulate`` and the virtual Prime's tunables (``ring_options`` reads them back)."""
    parser.add_argument("--emulate", action="store_true", help=emulate_help)
    parser.add_argument("--truth", metavar="FILE",
                        help="(with --emulate) the virtual robot's wiring and factory offsets, as a calibration file")
    parser.add_argument("--dc-lock-cycles", type=int, metavar="N", help="(with --emulate) DC lock cycles per drive")
    parser.add_argument("--mailbox-latency", type=float, metavar="S",
                        help="(with --emulate) time each emulated drive takes to answer an SDO (default 0.0005)")


def ring_options(args: argparse.Namespace, **more: object) -> dict[str, Any]:
    """The emulator tunables given on the command line; any of them, or a truthy ``more`` option (named as on
    the command line), without --emulate is an error."""
    given = {"--truth": args.truth, "--dc-lock-cycles": args.dc_lock_cycles,
             "--mailbox-latency": args.mailbox_latency, **more}
    used = [name for name, value in given.items() if value is not None and value is not False]
    if used and not args.emulate:
        raise PrimeError(f"{', '.join(used)}: only with --emulate (these act on the virtual Prime)")
    options: dict[str, Any] = {}
    if args.dc_lock_cycles is not None:
        options["dc_lock_cycles"] = args.dc_lock_cycles
    if args.mailbox_latency is not None:
        options["mailbox_latency_s"] = args.mailbox_latency
    return options


def output_file(text: str) -> Path:
    """argparse type of an output file: refused at once if it could not be written at the end of the run."""
    problem = output_problem(text)
    if problem is not None:
        raise argparse.ArgumentTypeError(f"cannot write there: {problem}")
    return Path(text).expanduser()


def output_dir(text: str) -> Path:
    """argparse type of an output folder, checked like ``output_file``."""
    problem = output_problem(text, directory=True)
    if problem is not None:
        raise argparse.ArgumentTypeError(f"cannot write there: {problem}")
    return Path(text).expanduser()


def add_json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON")


def print_json(data: Any) -> None:
    json.dump(data, sys.stdout, indent=2)
    sys.stdout.write("\n")
