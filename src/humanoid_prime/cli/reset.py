"""``prime reset``: the operator's fault reset on a running ``prime sim``, ``bringup`` or ``calibrate``."""

from __future__ import annotations

import argparse

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_json_option, add_socket_option, print_json
from humanoid_prime.runtime.socket import send_reset_request


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("reset", help=summary("reset"),
                              description="A drive fault latches until the operator resets it. This asks the "
                                          "running prime sim, bringup or calibrate to send every faulted drive a "
                                          "fault reset with its next frame and to enter the active mode again from "
                                          "the measured pose (r in its live table does the same). A drive whose "
                                          "cause persists faults again.")
    add_socket_option(p)
    add_json_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    faults = send_reset_request(args.socket)
    if args.json:
        print_json({"reset": faults})
    elif faults:
        print(f"reset sent to {len(faults)} faulted drive{'s' if len(faults) != 1 else ''}:")
        for fault in faults:
            print(f"  {fault}")
    else:
        print("no drive was in fault; the active mode was entered again")
    return 0
