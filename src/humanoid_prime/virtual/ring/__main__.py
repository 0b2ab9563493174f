"""``python -m humanoid_prime.virtual.ring --iface IF --control PATH [options]``: serve an emulated
ring on an existing interface until SIGTERM, SIGINT or a ``stop`` control request."""

from __future__ import annotations

import argparse
import socket
import sys
import time

from humanoid_prime.errors import PrimeError
from humanoid_prime.virtual.ring.options import RingOptions
from humanoid_prime.virtual.ring.ring import Ring
from humanoid_prime.virtual.ring.server import EmulatorServer, bring_up, run_until_signalled


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m humanoid_prime.virtual.ring",
                                     description="Serve an emulated eRob EtherCAT ring on a network interface.")
    parser.add_argument("--iface", required=True, help="interface the master's frames arrive on")
    parser.add_argument("--control", required=True, metavar="PATH", help="UNIX socket for the control channel")
    parser.add_argument("--wait-iface", type=float, default=0.0, metavar="SECONDS",
                        help="wait this long for the interface to appear (it may be moved in after start)")
    parser.add_argument("--parent-fd", type=int, metavar="FD",
                        help="read end of a pipe from the parent: exit when it closes (the parent died)")
    RingOptions.add_arguments(parser)
    return parser


def wait_for_interface(name: str, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while True:
        try:
            socket.if_nametoindex(name)  # asks this network namespace (sysfs may show another one)
            return True
        except OSError:
            pass
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.005)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        options = RingOptions.from_args(args)
    except ValueError as exc:
        print(f"emulator: {exc}", file=sys.stderr)
        return 2
    if not wait_for_interface(args.iface, args.wait_iface):
        print(f"emulator: interface {args.iface} does not exist", file=sys.stderr)
        return 1
    try:
        bring_up(args.iface)
        server = EmulatorServer(Ring(options), args.iface, args.control, parent_fd=args.parent_fd)
    except OSError as exc:
        print(f"emulator: cannot serve on {args.iface}: {exc} (raw sockets need root or CAP_NET_RAW)",
              file=sys.stderr)
        return 1
    except PrimeError as exc:
        print(f"emulator: {exc}", file=sys.stderr)
        return 1

    run_until_signalled(server)
    return 0


if __name__ == "__main__":
    sys.exit(main())
