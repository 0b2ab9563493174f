"""``prime switch MODE``: switch the mode of a running ``prime sim`` or ``prime bringup``."""

from __future__ import annotations

import argparse
import sys

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_json_option, add_socket_option, print_json, real
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.socket import MAX_WAIT_S, send_mode_request
from humanoid_prime.runtime.switching import describe

DEFAULT_WAIT_S = 10.0  # a mode switch on the robot takes well under a second; a loaded host far less than this


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("switch", help=summary("switch"),
                              description="Switch the control mode of a running prime sim or prime bringup "
                                          "from another terminal. The switch lands between two ticks; the command "
                                          "waits until the mode is active (on the robot: its eRob gains applied) "
                                          "and exits 0, or exits 1 saying why it was refused or fell back.")
    p.add_argument("mode", help="ZERO_TORQUE, DAMPING, STANDBY, LOCOMOTION or REMOTE")
    p.add_argument("--timeout", type=real(above=0.0, at_most=MAX_WAIT_S), default=DEFAULT_WAIT_S, metavar="S",
                   help=f"how long to wait for the outcome (default {DEFAULT_WAIT_S:g} s)")
    p.add_argument("--no-wait", action="store_true", help="only ask for the mode; do not wait for the outcome")
    add_socket_option(p)
    add_json_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        mode = Mode.parse(args.mode)
    except ValueError as exc:
        raise PrimeError(str(exc)) from None
    answer = send_mode_request(mode, args.socket, wait=0.0 if args.no_wait else args.timeout)
    done = answer["outcome"] in ("requested", "active")
    if args.json:
        print_json({key: value for key, value in answer.items() if key != "ok"})  # the socket's own "ok" left out
    elif done:
        print(describe(answer))
    if not done:
        print(f"prime switch: {describe(answer)}", file=sys.stderr)
    return 0 if done else 1
