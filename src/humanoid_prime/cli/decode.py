"""``prime decode``: read a CiA402 statusword, an eRob error code, or an EtherCAT AL status."""

from __future__ import annotations

import argparse

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_json_option, print_json
from humanoid_prime.drivers.erob.cia402 import ERROR_HINTS, describe_error, drive_state, set_bits
from humanoid_prime.drivers.ethercat.wire import describe_al_state, describe_al_status_code


def _word(text: str) -> int:
    """A 16-bit value written in decimal or 0x hex."""
    try:
        value = int(text, 16) if text.lower().startswith("0x") else int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; write it in decimal or 0x hex") from None
    if not 0 <= value <= 0xFFFF:
        raise argparse.ArgumentTypeError(f"{text} is outside 0..0xFFFF")
    return value


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("decode", help=summary("decode"),
                              description="Decode values read off a drive. Numbers in decimal or 0x hex.")
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    for name, help_text, func in (
        ("statusword", "CiA402 statusword (0x6041), e.g. 5687", _statusword),
        ("error", "eRob error code (0x603F), e.g. 0xA000", _error),
        ("al-status", "EtherCAT AL status code (register 0x0134), e.g. 0x001A", _al_status),
        ("al-state", "EtherCAT AL state (register 0x0130), e.g. 0x14", _al_state),
    ):
        k = kinds.add_parser(name, help=help_text, description=f"Decode a {help_text}.")
        k.add_argument("value", type=_word, metavar="N", help="the value, decimal or 0x hex")
        add_json_option(k)
        k.set_defaults(func=func)


def _show(args: argparse.Namespace, result: dict, text: str) -> int:
    if args.json:
        print_json(result)
    else:
        print(text)
    return 0


def _statusword(args: argparse.Namespace) -> int:
    state = drive_state(args.value).value
    bits = set_bits(args.value)
    result = {"statusword": args.value, "hex": f"0x{args.value:04X}", "state": state, "bits": bits}
    return _show(args, result, f"0x{args.value:04X} ({args.value}): {state}; bits set: {', '.join(bits) or 'none'}")


def _error(args: argparse.Namespace) -> int:
    meaning = describe_error(args.value)
    hint = ERROR_HINTS.get(args.value)
    result = {"code": args.value, "hex": f"0x{args.value:04X}", "meaning": meaning, "hint": hint}
    return _show(args, result, f"0x{args.value:04X}: {meaning}" + (f" — {hint}" if hint else ""))


def _al_status(args: argparse.Namespace) -> int:
    meaning = describe_al_status_code(args.value)
    result = {"code": args.value, "hex": f"0x{args.value:04X}", "meaning": meaning}
    return _show(args, result, f"AL status 0x{args.value:04X}: {meaning}")


def _al_state(args: argparse.Namespace) -> int:
    state = describe_al_state(args.value)
    result = {"value": args.value, "hex": f"0x{args.value:02X}", "state": state}
    return _show(args, result, f"AL state 0x{args.value:02X}: {state}")
