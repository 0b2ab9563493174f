"""``prime switch MODE``: switch the mode of a running ``prime sim`` or ``prime bringup``."""

from __future__ import annotations

import argparse

from humanoid_prime.cli._common import add_json_option, add_socket_option, print_json
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.socket import send_mode_request


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("switch", help="switch the mode of a running prime sim or bringup",
                              description="Switch the control mode of a running prime sim or prime bringup "
                                          "from another terminal. The switch lands between two ticks.")
    p.add_argument("mode", help="ZERO_TORQUE, DAMPING, STANDBY, LOCOMOTION or REMOTE")
    add_socket_option(p)
    add_json_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        mode = Mode.parse(args.mode)
    except ValueError as exc:
        raise PrimeError(str(exc)) from None
    accepted = send_mode_request(mode, args.socket)
    if args.json:
        print_json({"mode": accepted})
    else:
        print(f"requested {accepted}")
    return 0
