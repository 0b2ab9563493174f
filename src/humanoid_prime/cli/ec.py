"""``prime ec scan`` and ``prime ec sdo read|write``: EtherCAT commissioning.

``--backend soem`` opens the NIC in this process (nothing else may own it) and, where the ring matches the
hardware file, brings it to OP before any SDO. ``--backend igh`` asks a running IgH master through its
``ethercat`` tool.
"""

from __future__ import annotations

import argparse
import math
import time
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, NotRequired, TypedDict

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_config_options, add_json_option, add_mailbox_option, print_json, whole
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.drivers.erob.cia402 import describe_error, drive_state
from humanoid_prime.drivers.erob.objects import ERROR_CODE, RATED_TORQUE, STATUSWORD
from humanoid_prime.drivers.ethercat.errors import RingError, SdoError
from humanoid_prime.drivers.ethercat.igh import IGH_TYPES, SHORT_TYPES, IghSdo
from humanoid_prime.drivers.ethercat.ring import SlaveInfo, check_ring, expected_ring
from humanoid_prime.drivers.ethercat.sdo import SDO_BACKENDS, open_sdo
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient, read_error_history, write_fitting
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, describe_al_status_code
from humanoid_prime.errors import PrimeError

if TYPE_CHECKING:  # the master is imported by the scan that runs one (the CLI starts without it)
    from humanoid_prime.drivers.ethercat.master import EthercatMaster

_SCAN_CYCLES = 5  # exchanges after OP before statusword and error code are read from the process data


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    ec = subparsers.add_parser(
        "ec", help=summary("ec"),
        description="--backend soem opens the NIC in this process (nothing else may own it) and brings the ring "
                    "to OP before any SDO; --backend igh asks a running IgH master through its `ethercat` tool.")
    commands = ec.add_subparsers(dest="ec_command", metavar="COMMAND", required=True)

    scan = commands.add_parser(
        "scan", help="slaves, identity, AL state, statusword and error code",
        description="List the slaves on the ring with identity and AL state, check them against the hardware "
                    "file, and (when they match) bring the ring to OP to show each drive's statusword and error "
                    "code. Exits 1 when the ring does not match or does not reach OP.")
    scan.add_argument("--history", action="store_true", help="also read each drive's error history (0x1003)")
    _common_options(scan)
    scan.set_defaults(func=run_scan)

    sdo = commands.add_parser("sdo", help="read or write one object entry of one slave")
    ops = sdo.add_subparsers(dest="sdo_command", metavar="OP", required=True)
    read = ops.add_parser("read", help="upload one object entry",
                          description="Upload one object entry, e.g. `prime ec sdo read 3 0x603F:0`.")
    write = ops.add_parser("write", help="download one object entry (read back afterwards)",
                           description="Download one value, e.g. `prime ec sdo write 3 0x2383:0 1 --type u8`, "
                                       "then read it back. Without --type the object's current size is kept.")
    for p in (read, write):
        p.add_argument("ring", type=whole(at_least=0), metavar="RING", help="ring position of the slave (0 = first)")
        p.add_argument("address", metavar="INDEX:SUB", help="object index and subindex in hex, e.g. 0x2382:01")
        if p is write:
            p.add_argument("value", metavar="VALUE", help="integer value (0x prefix for hex)")
        p.add_argument("--type", choices=tuple(SHORT_TYPES), help="data type (default: the object's own)")
        _common_options(p)
    read.set_defaults(func=run_sdo_read)
    write.set_defaults(func=run_sdo_write)


def _common_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--interface", metavar="NIC", help="EtherCAT NIC (default: buses.ethercat.interface)")
    p.add_argument("--backend", choices=SDO_BACKENDS, default="soem",
                   help="soem: open the NIC here (default); igh: ask a running IgH master via `ethercat`")
    add_mailbox_option(p)
    add_config_options(p, controllers=True)
    add_json_option(p)


def parse_address(text: str) -> tuple[int, int]:
    """``0x2382:01`` / ``2382:1`` -> (0x2382, 1); index and subindex are hex, as CiA writes them."""
    index_text, sep, sub_text = text.partition(":")
    try:
        index = int(index_text, 16)
        sub_index = int(sub_text, 16) if sep else 0
    except ValueError:
        raise PrimeError(f"object address {text!r} is not INDEX:SUB in hex (e.g. 0x2382:01)") from None
    if not 0 <= index <= 0xFFFF or not 0 <= sub_index <= 0xFF:
        raise PrimeError(f"object address {text!r} is out of range (index 0..0xFFFF, subindex 0..0xFF)")
    return index, sub_index


def _rates(args: argparse.Namespace, robot: Robot) -> tuple[float, float]:
    controllers = load_controllers(robot.names, args.controllers)
    return controllers.update_rate, controllers.bringup_rate


# ------------------------------------------------------------------------------------- scan
class SlaveRow(TypedDict):
    """One slave of ``prime ec scan``; the drive's words where it was asked (None: not asked)."""

    ring: int
    joint: str | None  # None: no joint of the hardware file sits there
    name: str
    vendor_id: str
    product_code: str
    revision: str
    is_erob: bool
    al_state: str
    al_error: bool
    al_status_code: str
    al_status: str
    statusword: int | None
    drive_state: str | None
    error_code: str | None
    error: str | None
    rated_torque_nm: float | None
    error_history: NotRequired[list[str]]  # with --history


class ScanReport(TypedDict):
    backend: str
    interface: str | None
    slaves: list[SlaveRow]
    ring_matches: bool
    bringup_seconds: float | None
    retried: list[str]  # why the ring was scanned or configured again
    mailbox: str | None
    mailbox_drops: dict[str, int]  # by why
    mailbox_given_up: int  # requests whose reply was given up on (asked again, or timed out)
    problem: str | None


def _row(slave: SlaveInfo, joints: dict[int, str]) -> SlaveRow:
    return {
        "ring": slave.position, "joint": joints.get(slave.position), "name": slave.name,
        "vendor_id": f"0x{slave.vendor_id:08X}", "product_code": f"0x{slave.product_code:08X}",
        "revision": f"0x{slave.revision:08X}", "is_erob": slave.is_erob,
        "al_state": slave.state_text, "al_error": bool(slave.al_state & AL_ERROR),
        "al_status_code": f"0x{slave.al_status_code:04X}", "al_status": describe_al_status_code(slave.al_status_code),
        "statusword": None, "drive_state": None, "error_code": None, "error": None, "rated_torque_nm": None,
    }


def _drive(row: SlaveRow, statusword: int, error_code: int) -> None:
    row["statusword"] = statusword
    row["drive_state"] = drive_state(statusword).value
    row["error_code"] = f"0x{error_code:04X}"
    row["error"] = describe_error(error_code)


def _scan_soem(args: argparse.Namespace, robot: Robot, report: ScanReport) -> None:
    from humanoid_prime.drivers.ethercat.soem_master import SoemMaster

    hw = robot.hardware
    joints = {pos: joint for joint, pos in hw.erob_slaves.items()}
    update_rate, bringup_rate = _rates(args, robot)
    master = SoemMaster(args.interface or hw.ethercat.interface, update_rate=update_rate,
                        bringup_rate=bringup_rate, mailbox=args.ec_mailbox or hw.ethercat.mailbox)
    report["interface"] = master.interface
    report["mailbox"] = master.mailbox
    with master:
        try:
            found = master.open()
        finally:
            report["retried"] = list(master.scan_reasons)  # ring scans SOEM made again (a slow ring)
        rows = [_row(s, joints) for s in found]
        report["slaves"] = rows
        expected = expected_ring(hw.erob_slaves)
        check_ring(found, expected, master.interface)
        report["ring_matches"] = True
        try:
            bringup = master.start(expected)
        except RingError:
            for row, slave in zip(rows, master.read_states(), strict=True):
                row.update(_row(slave, joints))
            raise
        finally:
            report["retried"] = [*master.scan_reasons, *master.configure_reasons]
            _mailbox_counts(report, master)
        report["bringup_seconds"] = round(bringup.seconds, 3)
        for _ in range(_SCAN_CYCLES):
            master.exchange()
            time.sleep(1.0 / update_rate)
        for row, slave in zip(rows, master.read_states(), strict=True):
            row.update(_row(slave, joints))
            _drive(row, int(master.inputs["statusword"][slave.position]),
                   int(master.inputs["error_code"][slave.position]))
            rated = float(master.rated_torque_nm[slave.position])
            row["rated_torque_nm"] = rated if math.isfinite(rated) else None
        if args.history:
            for row in rows:
                row["error_history"] = [f"0x{c:04X}" for c in master.error_history(row["ring"])]
        _mailbox_counts(report, master)


def _mailbox_counts(report: ScanReport, master: EthercatMaster) -> None:
    """What the mailboxes dropped, by why, and the requests whose reply they gave up on."""
    report["mailbox_drops"] = master.mailbox_drops()
    report["mailbox_given_up"] = master.mailbox_given_up()


def _scan_igh(args: argparse.Namespace, robot: Robot, report: ScanReport) -> None:
    from humanoid_prime.drivers.ethercat.igh import IghSdo

    hw = robot.hardware
    joints = {pos: joint for joint, pos in hw.erob_slaves.items()}
    sdo = IghSdo(hw.ethercat.master)
    report["interface"] = interface = f"IgH master {hw.ethercat.master}"
    found = sdo.slaves()
    rows = [_row(s, joints) for s in found]
    report["slaves"] = rows
    check_ring(found, expected_ring(hw.erob_slaves), interface)
    report["ring_matches"] = True
    for row in rows:
        position = row["ring"]
        statusword, _ = sdo.upload(position, STATUSWORD, 0, "uint16")
        error_code, _ = sdo.upload(position, ERROR_CODE, 0, "uint16")
        _drive(row, statusword, error_code)
        try:
            row["rated_torque_nm"] = sdo.upload(position, RATED_TORQUE, 0, "uint32")[0] / 1000.0
        except SdoError:
            row["rated_torque_nm"] = None  # reported as unknown; the drive answered the rest
        if args.history:
            row["error_history"] = [f"0x{code:04X}" for code in read_error_history(sdo, position)]


def run_scan(args: argparse.Namespace) -> int:
    robot = load_robot(args.hardware)
    report: ScanReport = {"backend": args.backend, "interface": None, "slaves": [], "ring_matches": False,
                              "bringup_seconds": None, "retried": [], "mailbox": None, "mailbox_drops": {},
                              "mailbox_given_up": 0, "problem": None}
    try:
        (_scan_igh if args.backend == "igh" else _scan_soem)(args, robot, report)
    except (RingError, SdoError) as exc:
        if not report["slaves"]:
            raise
        report["problem"] = str(exc)
    if args.json:
        print_json(report)
    else:
        _print_scan(report)
    return 0 if report["problem"] is None else 1


def _print_scan(report: ScanReport) -> None:
    rows = report["slaves"]
    head = f"EtherCAT ring on {report['interface']} ({report['backend']}): {len(rows)} slaves"
    if report["ring_matches"]:
        head += ", matches the hardware file"
    if report["bringup_seconds"] is not None:
        head += f", OP in {report['bringup_seconds']:.2f} s"
    print(head)
    for r in rows:
        line = (f"  ring {r['ring']:>2}  {r['joint'] or '-':<22} {r['name'] or '?':<12} "
                f"vendor {r['vendor_id']} product {r['product_code']}  {r['al_state']:<16}")
        if r["al_error"]:  # a code without the error indication is one the slave left set (ETG.1000.6: ignored)
            line += f" AL status {r['al_status_code']} {r['al_status']}"
        if r["statusword"] is not None:
            line += f" statusword {r['statusword']} ({r['drive_state']})  error {r['error_code']} {r['error']}"
        if r["rated_torque_nm"] is not None:
            line += f"  rated {r['rated_torque_nm']:g} N*m"
        if "error_history" in r:
            line += f"  history [{', '.join(r['error_history'])}]"
        print(line.rstrip())
    if report["mailbox"] is not None:
        drops = report["mailbox_drops"]
        print(f"mailboxes: {report['mailbox']}" + (
            f"; messages dropped: {drops['late']} late, {drops['other object']} for another object, "
            f"{drops['unrecognised']} unrecognised, {drops['malformed']} malformed" if drops else ""))
    for reason in report["retried"]:
        print(f"configured again: {reason}")
    if report["problem"]:
        print(f"problem: {report['problem']}")


# -------------------------------------------------------------------------------------- SDO
def _type(args: argparse.Namespace) -> str | None:
    return SHORT_TYPES[args.type] if args.type else None


def _decode(raw: bytes, type_name: str | None) -> tuple[int, int]:
    if type_name is None:
        return int.from_bytes(raw, "little"), len(raw)
    size, signed = IGH_TYPES[type_name]
    if len(raw) < size:
        raise PrimeError(f"the object holds {len(raw)} bytes, fewer than {type_name} needs ({size})")
    return int.from_bytes(raw[:size], "little", signed=signed), size


class SdoResult(TypedDict):
    """An object read (or written and read back) by ``prime ec sdo``."""

    ring: int
    index: str
    sub_index: int
    backend: str
    type: str
    value: int
    hex: str
    written: NotRequired[int]  # what was written, where it was


def _result(args: argparse.Namespace, index: int, sub_index: int, value: int, size: int,
            type_name: str | None) -> SdoResult:
    return {"ring": args.ring, "index": f"0x{index:04X}", "sub_index": sub_index, "backend": args.backend,
            "type": type_name or _UNSIGNED.get(size, f"{size} bytes"), "value": value,
            "hex": f"0x{value & ((1 << (8 * size)) - 1):0{2 * size}X}"}


_UNSIGNED = {1: "uint8", 2: "uint16", 4: "uint32"}


def _read(sdo: SdoClient, args: argparse.Namespace, index: int, sub_index: int) -> tuple[int, int]:
    type_name = _type(args)
    if isinstance(sdo, IghSdo):  # the igh backend's: typed uploads
        return sdo.upload(args.ring, index, sub_index, type_name)
    return _decode(sdo.sdo_read(args.ring, index, sub_index), type_name)


def _session(args: argparse.Namespace) -> AbstractContextManager[SdoClient]:
    robot = load_robot(args.hardware)
    update_rate, bringup_rate = _rates(args, robot)
    if not 0 <= args.ring < len(robot.hardware.erob_slaves):
        raise PrimeError(f"ring position {args.ring} is not on the ring of {robot.hardware.path.name} "
                         f"(0..{len(robot.hardware.erob_slaves) - 1})")
    return open_sdo(args.backend, robot, interface=args.interface, update_rate=update_rate,
                    bringup_rate=bringup_rate, mailbox=args.ec_mailbox)


def run_sdo_read(args: argparse.Namespace) -> int:
    index, sub_index = parse_address(args.address)
    with _session(args) as sdo:
        value, size = _read(sdo, args, index, sub_index)
    result = _result(args, index, sub_index, value, size, _type(args))
    if args.json:
        print_json(result)
    else:
        print(f"ring {args.ring} {result['index']}:{sub_index:02X} = {value} ({result['hex']}, {result['type']})")
    return 0


def run_sdo_write(args: argparse.Namespace) -> int:
    index, sub_index = parse_address(args.address)
    try:
        value = int(args.value, 0)
    except ValueError:
        raise PrimeError(f"VALUE {args.value!r} is not an integer (use 0x for hex)") from None
    type_name = _type(args)
    if value < 0 and (type_name is None or not IGH_TYPES[type_name][1]):
        raise PrimeError(f"VALUE {value} is negative; give --type with a signed type (int8, int16, int32) for a "
                         "signed object")
    with _session(args) as sdo:
        if isinstance(sdo, IghSdo):
            if type_name is None:
                _, size = sdo.upload(args.ring, index, sub_index)
                type_name = _UNSIGNED.get(size)
                if type_name is None:
                    raise SdoError(args.ring, index, sub_index, f"{size}-byte object; give --type")
            sdo.download(args.ring, index, sub_index, value, type_name)
        elif type_name is None:  # the size the drive holds it in; a narrower one if it refuses that length
            size = len(sdo.sdo_read(args.ring, index, sub_index))
            try:
                value.to_bytes(size, "little", signed=value < 0)
            except OverflowError:
                raise PrimeError(f"VALUE {value} does not fit {size} bytes") from None
            write_fitting(sdo, args.ring, (index, sub_index), value, size, signed=value < 0)
        else:
            size, signed = IGH_TYPES[type_name]
            try:
                data = value.to_bytes(size, "little", signed=signed)
            except OverflowError:
                raise PrimeError(f"VALUE {value} does not fit {type_name}") from None
            sdo.sdo_write(args.ring, index, sub_index, data)
        back, size = _read(sdo, args, index, sub_index)
    result = _result(args, index, sub_index, back, size, type_name)
    result["written"] = value
    if args.json:
        print_json(result)
    else:
        print(f"ring {args.ring} {result['index']}:{sub_index:02X} <- {value}; read back {back} ({result['hex']})")
    mask = (1 << (8 * size)) - 1
    return 0 if back & mask == value & mask else 1
