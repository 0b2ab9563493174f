"""``prime doctor``: check the host, the buses and the robot before anything moves, one line per check with
its fix. Reads only: the ring goes no further than PRE-OP and no wrist is enabled, unless ``--op``."""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import (
    add_config_options,
    add_emulation_options,
    add_json_option,
    output_file,
    print_json,
    real,
    ring_options,
    write_summary,
)
from humanoid_prime.doctor import BACKENDS
from humanoid_prime.drivers.erob.constants import MIN_CYCLE_S
from humanoid_prime.errors import PrimeError


def backends(text: str) -> tuple[str, ...]:
    """argparse type of ``--backends``: ``ec``, ``can``, ``ec,can`` or ``all``."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    if names == ["all"]:
        return BACKENDS
    unknown = [n for n in names if n not in BACKENDS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"{text!r}: give ec, can, ec,can or all")
    return tuple(b for b in BACKENDS if b in names)


def folder(text: str) -> Path:
    """argparse type of a folder that exists."""
    if not text or not Path(text).expanduser().is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is no folder")
    return Path(text).expanduser()


def input_file(text: str) -> Path:
    """argparse type of a file that exists."""
    if not text or not Path(text).expanduser().is_file():
        raise argparse.ArgumentTypeError(f"{text!r} is no file")
    return Path(text).expanduser()


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "doctor", help=summary("doctor"),
        description="Check the host (the ring's NIC, rights, real-time kernel, wake-up latency), the EtherCAT ring "
                    "(identities, firmware revisions, rated torque, errors), the CAN bus and wrists, and the "
                    "robot's files, one line per check: pass, warn or fail, what was found and the fix. Reads "
                    "only: the ring goes no further than PRE-OP and no wrist is enabled, unless --op. Exits 1 "
                    "when a check fails.")
    add_config_options(p, calibration=True, controllers=True)
    p.add_argument("--backends", type=backends, default=BACKENDS, metavar="ec,can",
                   help="the buses to check: ec, can or both (default both)")
    p.add_argument("--interface", metavar="NIC", help="EtherCAT NIC (default: buses.ethercat.interface)")
    p.add_argument("--rate", type=real(above=0.0, at_most=1.0 / MIN_CYCLE_S), metavar="HZ",
                   help="judge the wake-up latency against this rate's period too (the controllers file's "
                        "update_rate is always judged); with --op the ring runs at it")
    p.add_argument("--op", action="store_true",
                   help="go further: take the ring to OP as a bring-up does (drives disabled), and enable each "
                        "wrist limp (zero gains, zero current) to hear it; nothing is commanded to move")
    p.add_argument("--last-run", metavar="FILE", type=input_file,
                   help="the summary a run wrote (--summary): what it flagged, and the files it used")
    p.add_argument("--erob-config-dir", metavar="DIR", type=folder,
                   help="check the per-slave eRob configs folded there (prime calibration fold --output DIR) "
                        "against the calibration")
    add_emulation_options(p, "check the virtual Prime (both buses emulated, in a private network namespace) "
                             "instead of the robot")
    p.add_argument("--summary", metavar="FILE", type=output_file, help="also write the report as JSON")
    add_json_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    emulation = ring_options(args)  # refuses the emulator's options without --emulate
    if args.summary is not None and args.last_run is not None \
            and Path(args.summary).absolute().resolve() == Path(args.last_run).absolute().resolve():
        raise PrimeError(f"--summary {args.summary} is also --last-run, which this command reads; writing it would "
                         "destroy it: name another file")
    if args.emulate:  # before the checks' imports: this process is replaced by one in a namespace of its own
        from humanoid_prime.virtual.harness import enter_private_netns

        enter_private_netns()
    from humanoid_prime.doctor.robot import read_summary
    from humanoid_prime.doctor.run import DoctorOptions, run_doctor

    summary = read_summary(args.last_run) if args.last_run is not None else None
    options = DoctorOptions(files=args.config, backends=args.backends, interface=args.interface, rate=args.rate,
                            op=args.op, last_run=args.last_run, last_run_summary=summary,
                            folded_dir=args.erob_config_dir)
    with contextlib.ExitStack() as stack:
        if args.emulate:
            from humanoid_prime.virtual.harness import attach_virtual_prime

            began = time.monotonic()
            virtual = attach_virtual_prime(stack, hardware_file=args.hardware, truth_file=args.truth,
                                           ring_options=emulation)
            options.interface, options.interface_source = virtual.master_interface, "the virtual Prime's (--emulate)"
            options.can_interface, options.can_channel = virtual.can_interface, virtual.can_channel
            options.context["emulated"] = True
            options.context["emulator_start_s"] = round(time.monotonic() - began, 3)
        report = run_doctor(options)
    if args.json:
        print_json(report.as_dict())
    else:
        for line in report.lines():
            print(line)
    write_summary(args, report.as_dict())
    return 0 if report.ok else 1
