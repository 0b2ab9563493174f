"""The EtherCAT wire facts: AL states and status codes in words, each constant written once (``wire.py``), and no
lookup of another library's socket."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from humanoid_prime.drivers.ethercat import wire
from humanoid_prime.drivers.ethercat.wire import AL_STATUS_CODES, describe_al_state, describe_al_status_code

SRC = Path(wire.__file__).parents[2]
ROOMS = (SRC / "drivers", SRC / "virtual")
WIRE_PREFIXES = ("REG_", "AL_", "ETHERTYPE", "MAILBOX_TYPE_", "COE_", "SDO_", "EEPROM_", "ABORT_", "SII_WORD", "SCS_",
                 "CCS_")


@pytest.mark.parametrize("code, meaning", [
    (0x0000, "no error"),
    (0x0011, "invalid requested state change"),
    (0x0012, "unknown requested state"),
    (0x001A, "synchronization error"),
    (0x001B, "sync manager watchdog"),
    (0x001D, "invalid output configuration"),
    (0x001E, "invalid input configuration"),
    (0x002C, "fatal sync error"),
    (0x002D, "no sync error"),
    (0x0030, "invalid DC SYNC configuration"),
    (0x0032, "PLL error"),
    (0x0035, "DC invalid sync cycle time"),
    (0x0036, "DC invalid SYNC0 cycle time"),
])
def test_al_status_codes(code, meaning):
    assert describe_al_status_code(code) == meaning


def test_unknown_al_status_code_is_named():
    assert describe_al_status_code(0x0099) == "unknown AL status code 0x0099"
    assert 0x0099 not in AL_STATUS_CODES


@pytest.mark.parametrize("value, name", [(1, "INIT"), (2, "PRE-OP"), (3, "BOOT"), (4, "SAFE-OP"), (8, "OP"),
                                         (0x14, "SAFE-OP + ERROR"), (0x12, "PRE-OP + ERROR")])
def test_al_states(value, name):
    assert describe_al_state(value) == name


def module_constants(path: Path) -> dict[str, int]:
    """Module-level names bound to an integer literal in ``path`` (tuple assignments too)."""
    found: dict[str, int] = {}
    for node in ast.parse(path.read_text()).body:
        if not isinstance(node, ast.Assign):
            continue
        for target in node.targets:
            names = target.elts if isinstance(target, ast.Tuple) else [target]
            values = node.value.elts if isinstance(node.value, ast.Tuple) else [node.value]
            for name, value in zip(names, values, strict=False):
                if isinstance(name, ast.Name) and isinstance(value, ast.Constant) and type(value.value) is int:
                    found[name.id] = value.value
    return found


def test_no_wire_constant_is_defined_outside_wire_py():
    wire_names = set(module_constants(Path(wire.__file__))) | {name for name in vars(wire) if name.isupper()}
    twice = []
    for room in ROOMS:
        for path in sorted(room.rglob("*.py")):
            if path == Path(wire.__file__):
                continue
            for name in module_constants(path):
                if name in wire_names or name.startswith(WIRE_PREFIXES):
                    twice.append(f"{path.relative_to(SRC)}: {name}")
    assert twice == []


def test_no_module_looks_up_another_library_s_socket_in_proc():
    lookups = [f"{path.relative_to(SRC)}" for path in sorted(SRC.rglob("*.py"))
               if "/proc/net/packet" in path.read_text() or "/proc/self/fd" in path.read_text()]
    assert lookups == []
