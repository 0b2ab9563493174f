"""``prime emulate ec``: the ten eRob as an EtherCAT ring a real master (SOEM) can open, no robot needed.

``--veth`` creates a veth pair, runs the ring on one end inside a private network namespace and prints
the other end for the master; ``--interface IF`` serves an existing interface in this process. Either
runs in the foreground until Ctrl-C and cleans up. Without root, ``--veth`` re-runs itself under
``unshare -rn``; the master end then exists only inside that namespace, so give the master's command
after ``--`` ({iface} in it is replaced by the interface; PRIME_EC_INTERFACE and PRIME_EC_CONTROL are
set for it).
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_config_options
from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.errors import PrimeError
from humanoid_prime.virtual.netns import EmulatedRing, netns_unavailable_reason, reexec_in_user_netns
from humanoid_prime.virtual.ring import __main__ as emulator_main
from humanoid_prime.virtual.ring.options import RingOptions


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("emulate", help=summary("emulate"),
                              description="Emulated hardware a real driver can talk to.")
    kinds = p.add_subparsers(dest="emulate_kind", metavar="KIND", required=True)
    ec = kinds.add_parser(
        "ec", help="an EtherCAT ring of eRob drives on a veth pair or an interface",
        description="An EtherCAT ring of emulated eRob drives answering a real master frame by frame. --veth "
                    "creates a veth pair (root, or user namespaces) and names the master's end on stderr; "
                    "--interface serves an existing interface. Runs until Ctrl-C, or until the command after -- "
                    "exits: in that command {iface} stands for the master's interface (also in $PRIME_EC_INTERFACE, "
                    "the control socket in $PRIME_EC_CONTROL), e.g. `prime emulate ec --veth -- prime ec scan "
                    "--interface {iface} --json`; its stdout is its own.")
    where = ec.add_mutually_exclusive_group(required=True)
    where.add_argument("--veth", action="store_true", help="create a veth pair in a private network namespace")
    where.add_argument("--interface", "--iface", metavar="IF", help="serve this existing interface (needs root)")
    ec.add_argument("--control", metavar="PATH", help="control socket path for --interface (default: a temp file)")
    RingOptions.add_arguments(ec)
    add_config_options(ec)
    ec.add_argument("master_command", nargs=argparse.REMAINDER, metavar="-- CMD",
                    help="run this master command against the ring, then stop; {iface} is replaced by the master's "
                         "interface")
    ec.set_defaults(func=run_ec)


def _options(args: argparse.Namespace) -> RingOptions:
    try:
        return RingOptions.from_args(args)
    except ValueError as exc:
        raise PrimeError(f"{exc}") from None


def _master_command(args: argparse.Namespace) -> list[str]:
    command = list(args.master_command)
    if command and command[0] == "--":
        command = command[1:]
    return command


def run_ec(args: argparse.Namespace) -> int:
    options = _options(args)
    command = _master_command(args)
    if args.interface:
        return _serve_interface(args, options, command)
    reason = netns_unavailable_reason()
    if reason is not None:
        if os.geteuid() != 0 and "unshare -rn" in reason:
            if not command:
                raise PrimeError("without root the master end of the veth pair exists only inside a private "
                                 "namespace: give the master's command after --, e.g. "
                                 "`prime emulate ec --veth -- prime ec scan --interface {iface}`, or run as root")
            reexec_in_user_netns()
        raise PrimeError(f"{reason}")
    with EmulatedRing(**vars(options)) as ring:
        print(f"emulating {options.slaves} eRob; master interface: {ring.master_interface}; "
              f"control socket: {ring.control.path}", file=sys.stderr, flush=True)
        if command:
            return _run_master(command, ring.master_interface, ring.control.path)
        try:
            while ring.running:
                time.sleep(0.2)
        except KeyboardInterrupt:
            print("stopped", file=sys.stderr, flush=True)
            return 0
    raise PrimeError("the emulator stopped unexpectedly")


def _run_master(command: list[str], interface: str, control: str) -> int:
    environment = dict(os.environ, PRIME_EC_INTERFACE=interface, PRIME_EC_CONTROL=control)
    try:
        return subprocess.run([part.replace("{iface}", interface) for part in command], env=environment).returncode
    except FileNotFoundError:
        raise PrimeError(f"command {command[0]!r} not found") from None
    except KeyboardInterrupt:
        return 130


def _serve_interface(args: argparse.Namespace, options: RingOptions, command: list[str]) -> int:
    if command:
        raise PrimeError("a master command after -- needs --veth (with --interface the master runs "
                         "wherever the interface's other end is)")
    robot_nic = load_hardware(args.hardware).ethercat.interface
    if args.interface == robot_nic:
        raise PrimeError(f"refusing to emulate on {robot_nic}, the robot's EtherCAT NIC (buses.ethercat.interface); "
                         "use --veth or another interface")
    _check_servable(args.interface)
    control = args.control or os.path.join(tempfile.gettempdir(), f"prime-ec-{os.getpid()}.sock")
    print(f"emulating {options.slaves} eRob on {args.interface}; control socket: {control}", file=sys.stderr,
          flush=True)
    # a failure past the checks is the emulator's one line ("emulator: ..."), not followed by another
    return emulator_main.main(["--iface", args.interface, "--control", control, *options.to_args()])


def _check_servable(interface: str) -> None:
    """Refuse, in one line and before anything is printed, an interface the ring cannot serve: one that does not
    exist, or one this process may not open a raw socket on."""
    try:
        socket.if_nametoindex(interface)
    except OSError:
        raise PrimeError(f"no network interface {interface!r} to serve (--interface); list them with `ip link`, or "
                         "use --veth") from None
    try:
        socket.socket(socket.AF_PACKET, socket.SOCK_RAW).close()
    except PermissionError:
        raise PrimeError(f"serving {interface} needs a raw socket: run as root (or with CAP_NET_RAW), or use "
                         "--veth") from None
