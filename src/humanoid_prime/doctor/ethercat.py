"""The EtherCAT checks: the ring as the hardware file says it, and what each drive says of itself, read with the
ring in PRE-OP.

The ring is scanned by the master the bring-up uses (``SoemMaster.open``: slaves end in PRE-OP) and each drive's
objects are uploaded through its own mailbox (``PreopSdo``). PRE-OP is a state in which a master may talk to a
slave's mailbox freely: no SyncManager, FMMU or SYNC0 is set up yet, so there is no distributed clock to disturb
(the 0xA000 of DESIGN §3 comes from mailbox traffic while SYNC0 locks, long after). Nothing is written to a drive.
Only ``--op`` takes the ring further: Prime's PDO mapping, SYNC0 and OP, as any bring-up does, with the drives kept
disabled.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

from humanoid_prime.config.hardware import HardwareConfig
from humanoid_prime.doctor.report import Check, failed, not_run, passed, warned
from humanoid_prime.drivers.erob.cia402 import DriveState, describe_error, drive_state
from humanoid_prime.drivers.erob.objects import ERROR_CODE, RATED_TORQUE, STATUSWORD
from humanoid_prime.drivers.erob.tested import EROB_MODELS, TESTED_REVISIONS, model_for, model_reading
from humanoid_prime.drivers.ethercat.errors import RingError, SdoError
from humanoid_prime.drivers.ethercat.mailbox import CoeMailbox, MailboxLayout
from humanoid_prime.drivers.ethercat.mapping import mailbox_sync_managers
from humanoid_prime.drivers.ethercat.registers import NoReply, RingRegisters
from humanoid_prime.drivers.ethercat.ring import ExpectedSlave, SlaveInfo, check_ring, expected_ring
from humanoid_prime.drivers.ethercat.sdo_client import read_error_history
from humanoid_prime.drivers.ethercat.wire import (
    AL_ERROR,
    ESC_FEATURE_DC,
    REG_ESC_FEATURES,
    AlState,
    describe_al_status_code,
)
from humanoid_prime.errors import PrimeError

GROUP = "ethercat"
SOFTWARE_VERSION = 0x100A  # manufacturer software version (CiA 301), a visible string
SDO_TIMEOUT_S = 0.7
PRE_OP_RATE_HZ = 50.0  # what the master is made with where no rate is known: nothing runs cyclic in PRE-OP
OP_CYCLES = 5  # exchanges in OP before the drives' statuswords are read from the process data
CHECKS = ("scan", "identity", "revision", "al_status", "dc", "mailbox", "rated_torque", "errors", "history")


class PreopSdo:
    """SDO uploads to the slaves of a ring in PRE-OP, each through its own mailbox (as SM0/SM1 describe it), over
    the master's register channels. An ``SdoClient`` that writes nothing: ``sdo_write`` refuses."""

    def __init__(self, registers: RingRegisters, timeout_s: float = SDO_TIMEOUT_S) -> None:
        self.registers = registers
        self.timeout_s = timeout_s
        self._mailboxes: dict[int, CoeMailbox] = {}

    def _mailbox(self, position: int, index: int, sub: int) -> CoeMailbox:
        if position not in self._mailboxes:
            try:
                layout = MailboxLayout(*mailbox_sync_managers(self.registers, position))
            except NoReply as exc:
                raise SdoError(position, index, sub, f"its mailbox could not be found: {exc.what}") from None
            self._mailboxes[position] = CoeMailbox(self.registers.channel(position), position,
                                                   self.registers.stations[position], layout)
        return self._mailboxes[position]

    def sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        return self._mailbox(position, index, sub_index).upload(index, sub_index, self.timeout_s)

    def sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        raise PrimeError("prime doctor writes to no drive")


@dataclass
class DriveReading:
    """What one eRob said of itself in PRE-OP; a ``*_problem`` says why a value could not be read."""

    slave: SlaveInfo
    joint: str
    dc: bool | None = None
    software: str | None = None
    rated_torque_nm: float | None = None
    rated_problem: str = ""
    error_code: int | None = None
    statusword: int | None = None
    error_problem: str = ""
    history: list[int] | None = None
    history_problem: str = ""
    problems: list[str] = field(default_factory=list)


def _u(raw: bytes, size: int) -> int:
    return int.from_bytes(raw[:size].ljust(size, b"\0"), "little")


def read_drive(sdo: PreopSdo, registers: RingRegisters, slave: SlaveInfo, joint: str) -> DriveReading:
    """Everything the checks need from the drive at ``slave.position``: ESC features, 0x100A, 0x6076, 0x603F,
    0x6041 and 0x1003; each read on its own, so one refusal leaves the others."""
    k = slave.position
    reading = DriveReading(slave, joint)
    try:
        reading.dc = bool(struct.unpack("<H", registers.read_agreed(k, REG_ESC_FEATURES, 2))[0] & ESC_FEATURE_DC)
    except NoReply:
        reading.dc = None
    try:
        reading.software = sdo.sdo_read(k, SOFTWARE_VERSION, 0).decode("ascii", errors="replace").strip("\0 ")
    except SdoError:
        reading.software = None  # optional in CiA 301: its absence is no problem
    try:
        raw = sdo.sdo_read(k, RATED_TORQUE, 0)
        reading.rated_torque_nm = _u(raw, 4) / 1000.0
    except SdoError as exc:
        reading.rated_problem = exc.problem
    try:
        reading.error_code = _u(sdo.sdo_read(k, ERROR_CODE, 0), 2)
        reading.statusword = _u(sdo.sdo_read(k, STATUSWORD, 0), 2)
    except SdoError as exc:
        reading.error_problem = f"0x{exc.index:04X}: {exc.problem}"
    try:
        reading.history = read_error_history(sdo, k)
    except SdoError as exc:
        reading.history_problem = exc.problem
    return reading


def _joints(readings: Sequence[DriveReading]) -> str:
    return ", ".join(f"ring {r.slave.position} ({r.joint})" for r in readings)


# ----------------------------------------------------------------------------------------------------- the ring
def scan_check(found: Sequence[SlaveInfo], expected: Sequence[ExpectedSlave], interface: str) -> Check:
    states = {s.state_text for s in found}
    where = f"{len(found)} slaves on {interface}, in {', '.join(sorted(states))}"
    if len(found) != len(expected):
        return failed(GROUP, "scan", f"{where}; the hardware file places {len(expected)}",
                      "power every drive and check the cable between the last one that answers and the next; "
                      "`prime ec scan` lists what answers")
    return passed(GROUP, "scan", where)


def identity_check(found: Sequence[SlaveInfo], expected: Sequence[ExpectedSlave], interface: str,
                   hardware_path: str) -> Check:
    try:
        check_ring(found, expected, interface)
    except RingError as exc:
        text = str(exc)
        cut = text.find("; fix the cabling order")
        return failed(GROUP, "identity", text[:cut] if cut > 0 else text,
                      f"fix the cabling order, or joints.erob_slaves in {hardware_path}")
    return passed(GROUP, "identity", f"ring 0-{len(found) - 1} hold eRob (vendor 0x{expected[0].vendor_id:08X}, "
                                     f"product 0x{expected[0].product_code:08X}) where joints.erob_slaves puts them"
                  if found else "no slave expected")


def revision_check(readings: Sequence[DriveReading]) -> Check:
    by_revision: dict[int, list[DriveReading]] = {}
    for r in readings:
        by_revision.setdefault(r.slave.revision, []).append(r)
    software = sorted({r.software for r in readings if r.software})
    text = "; ".join(f"revision 0x{rev:08X} on {len(rs)} drives" for rev, rs in sorted(by_revision.items()))
    text += f" (software {', '.join(software)})" if software else ""
    untested = [r for r in readings if r.slave.revision not in TESTED_REVISIONS]
    if not untested:
        return passed(GROUP, "revision", f"{text}: a revision Prime is tested with")
    tested = ", ".join(f"0x{rev:08X}" for rev in TESTED_REVISIONS)
    return warned(GROUP, "revision", f"{_joints(untested)}: revision "
                                     f"{', '.join(sorted({f'0x{r.slave.revision:08X}' for r in untested}))}, not "
                                     f"one Prime is tested with ({tested}, drivers/erob/tested.py)",
                  "bring it up with care (prime bringup --backends ec, then a mode switch), or flash a tested "
                  "firmware with ZeroErr's tool")


def al_status_check(found: Sequence[SlaveInfo]) -> Check:
    raised = [s for s in found if s.al_state & AL_ERROR]
    left = [s for s in found if s.al_status_code and not s.al_state & AL_ERROR]
    if raised:
        what = "; ".join(f"ring {s.position} {s.state_text} AL status 0x{s.al_status_code:04X} "
                         f"({describe_al_status_code(s.al_status_code)})" for s in raised)
        return failed(GROUP, "al_status", f"{what}", "power-cycle the drive if it stays; `prime decode al-status "
                                                     f"0x{raised[0].al_status_code:04X}` says what it means")
    if left:
        what = "; ".join(f"ring {s.position} 0x{s.al_status_code:04X} ({describe_al_status_code(s.al_status_code)})"
                         for s in left)
        return warned(GROUP, "al_status", f"AL status code left set with no error flag: {what} (an earlier "
                                          "session's error, or a slave that does not clear it)")
    return passed(GROUP, "al_status", "no AL status code set")


def dc_check(readings: Sequence[DriveReading]) -> Check:
    none = [r for r in readings if r.dc is False]
    unread = [r for r in readings if r.dc is None]
    if none:
        return failed(GROUP, "dc", f"{_joints(none)}: no distributed clock; eRob CSP needs DC (free run faults "
                                   "the drive with 4616)", "replace the drive, or check it is an eRob")
    if unread:
        return warned(GROUP, "dc", f"{_joints(unread)}: the ESC's feature register (0x0008) did not answer")
    return passed(GROUP, "dc", f"every drive's ESC has a distributed clock ({len(readings)})")


def mailbox_check(hardware: HardwareConfig) -> Check:
    """Which layer does the bring-up's mailbox work, as ``buses.ethercat.mailbox`` of ``hardware`` decides it."""
    if hardware.ethercat.mailbox == "soem":
        return warned(GROUP, "mailbox", f"SOEM does the mailbox work alone (buses.ethercat.mailbox: soem in "
                                        f"{hardware.path}), the way back: the bring-up's SDOs are neither matched to "
                                        "their requests nor are their drops counted and named",
                      "once the drive's replies are reported (`prime ec scan --ec-mailbox prime` counts the drops by "
                      "reason), remove buses.ethercat.mailbox")
    return passed(GROUP, "mailbox", "the bring-up's SDOs go through Prime's CoE layer beside SOEM "
                                    "(buses.ethercat.mailbox: prime)")


def _grouped(found: dict[str, list[DriveReading]]) -> str:
    """``{finding: drives}`` -> "ring 0 (a), ring 1 (b): finding; ...", each finding once."""
    return "; ".join(f"{_joints(drives)}: {finding}" for finding, drives in found.items())


def rated_torque_check(readings: Sequence[DriveReading], hardware: HardwareConfig) -> Check:
    wrong: dict[str, list[DriveReading]] = {}
    doubtful: dict[str, list[DriveReading]] = {}
    agree = []
    for r in readings:
        kt, gear = hardware.erob_kt[r.joint], hardware.erob_gear[r.joint]
        said = f"Kt {kt:g} N*m/mA, gear {gear:g} (joints.erob_kt/erob_gear)"
        if r.rated_torque_nm is None or r.rated_torque_nm == 0:
            doubtful.setdefault(f"0x6076 {r.rated_problem or 'reads 0'}", []).append(r)
            continue
        expected = model_for(kt, gear)
        reading = model_reading(r.rated_torque_nm)
        if expected is not None and reading is expected:
            agree.append(r)
        elif expected is not None:
            like = f", what an {reading.name} reports" if reading is not None else ""
            wrong.setdefault(f"reads {r.rated_torque_nm:g} N*m{like}; the hardware file's {said} is an "
                             f"{expected.name}, which reports {expected.rated_torque_nm:g}", []).append(r)
        else:
            doubtful.setdefault(f"reads {r.rated_torque_nm:g} N*m; no tested model has {said}", []).append(r)
    if wrong:
        return failed(GROUP, "rated_torque", _grouped(wrong),
                      f"set each such joint's joints.erob_kt and joints.erob_gear in {hardware.path} to its model's "
                      "(the label on the actuator), or fit the model the file says")
    if doubtful:
        known = ", ".join(f"{m.name} {m.rated_torque_nm:g} N*m" for m in EROB_MODELS)
        return warned(GROUP, "rated_torque", f"{_grouped(doubtful)} (tested models: {known})",
                      "check each actuator's label against joints.erob_kt/erob_gear")
    values = sorted({r.rated_torque_nm for r in agree if r.rated_torque_nm is not None})
    return passed(GROUP, "rated_torque", f"0x6076 reads {', '.join(f'{v:g}' for v in values)} N*m on "
                                         f"{len(agree)} drives, as their Kt and gear in the hardware file say")


def errors_check(readings: Sequence[DriveReading]) -> Check:
    unread = [r for r in readings if r.error_code is None]
    faulted = [r for r in readings if (r.error_code or 0) != 0
               or (r.statusword is not None and drive_state(r.statusword) in (DriveState.FAULT,
                                                                              DriveState.FAULT_REACTION_ACTIVE))]
    if faulted:
        what = "; ".join(f"ring {r.slave.position} ({r.joint}) error 0x{r.error_code or 0:04X} "
                         f"({describe_error(r.error_code or 0)}), statusword 0x{r.statusword or 0:04X} "
                         f"({drive_state(r.statusword or 0).value})" for r in faulted)
        return failed(GROUP, "errors", what, "find the cause (`prime decode error CODE`), then reset it: "
                                             "`prime reset` while `prime bringup --backends ec` runs")
    if unread:
        return warned(GROUP, "errors", "; ".join(f"ring {r.slave.position} ({r.joint}): {r.error_problem}"
                                                 for r in unread))
    return passed(GROUP, "errors", f"no drive reports an error (0x603F 0, no fault in 0x6041) ({len(readings)})")


def history_check(readings: Sequence[DriveReading]) -> Check:
    unread = [r for r in readings if r.history is None]
    held = [r for r in readings if r.history]
    if held:
        what = "; ".join(f"ring {r.slave.position} ({r.joint}) "
                         + ", ".join(f"0x{c:04X} {describe_error(c)}" for c in (r.history or [])) for r in held)
        first = held[0].slave.position
        return warned(GROUP, "history", f"errors in the drives' history (0x1003, newest first): {what}",
                      f"read them again with `prime ec scan --history`; once understood, clear one drive's with "
                      f"`prime ec sdo write {first} 0x1003:0 0` (a write to the drive)")
    if unread:
        return warned(GROUP, "history", "; ".join(f"ring {r.slave.position} ({r.joint}): 0x1003 "
                                                  f"{r.history_problem}" for r in unread))
    return passed(GROUP, "history", f"no error in any drive's history (0x1003) ({len(readings)})")


# --------------------------------------------------------------------------------------------------------- the run
def ethercat_checks(hardware: HardwareConfig, interface: str, *, rates: tuple[float, float] | None,
                    op: bool = False) -> list[Check]:
    """Every EtherCAT check, against the ring on ``interface``: scanned into PRE-OP, read, and left in INIT (with
    ``op``, first taken to OP at ``rates``, SYNC0's and the bring-up loop's, with the drives disabled)."""
    from humanoid_prime.drivers.ethercat.soem_master import SoemMaster

    expected = expected_ring(hardware.erob_slaves)
    joints = {e.position: e.joint for e in expected}
    update_rate, bringup_rate = rates or (PRE_OP_RATE_HZ, PRE_OP_RATE_HZ)
    master = SoemMaster(interface, update_rate=update_rate, bringup_rate=bringup_rate)
    with master:
        try:
            found = master.open()
        except RingError as exc:
            return [failed(GROUP, "scan", str(exc), f"check the cable from {interface} to the first drive and the "
                                                    "drives' power; `prime ec scan` shows what answers"),
                    *(not_run(GROUP, name, "the ring could not be scanned") for name in CHECKS[1:])]
        checks = [scan_check(found, expected, interface),
                  identity_check(found, expected, interface, str(hardware.path))]
        erob = [s for s in found if s.is_erob and s.position in joints and s.al_state == AlState.PRE_OP]
        registers = master.registers
        assert registers is not None  # open() made them
        sdo = PreopSdo(registers)
        readings = [read_drive(sdo, registers, s, joints[s.position]) for s in erob]
        if readings:
            checks.append(revision_check(readings))
        else:
            checks.append(not_run(GROUP, "revision", "no eRob in PRE-OP where the hardware file expects one"))
        checks += [al_status_check(found), dc_check(readings) if readings else not_run(GROUP, "dc", "no eRob to ask"),
                   mailbox_check(hardware)]
        if readings:
            checks += [rated_torque_check(readings, hardware), errors_check(readings), history_check(readings)]
        else:
            checks += [not_run(GROUP, name, "no eRob to ask") for name in ("rated_torque", "errors", "history")]
        if op and rates is None:
            checks.append(not_run(GROUP, "op", "the controllers file did not load: no rate to run the ring at"))
        elif op:
            checks.append(op_check(master, expected, checks[1].verdict.value == "pass", joints))
    return checks


def op_check(master: object, expected: Sequence[ExpectedSlave], ring_matches: bool, joints: dict[int, str]) -> Check:
    """(``--op``) The ring to OP as a bring-up takes it, drives disabled; their statuswords from the process data."""
    from humanoid_prime.drivers.ethercat.soem_master import SoemMaster

    assert isinstance(master, SoemMaster)
    if not ring_matches:
        return not_run(GROUP, "op", "the ring does not match the hardware file")
    try:
        report = master.start(expected)
    except (RingError, PrimeError) as exc:
        return failed(GROUP, "op", f"the ring did not reach OP: {exc}", "`prime bringup --backends ec` shows the "
                                                                        "same bring-up with its live table")
    period = master.cycle_ns / 1e9
    for _ in range(OP_CYCLES):
        master.exchange()
        time.sleep(period)
    faulted = []
    for position in range(len(master.slaves)):
        statusword = int(master.inputs["statusword"][position])
        if drive_state(statusword) is DriveState.FAULT:
            code = int(master.inputs["error_code"][position])
            faulted.append(f"ring {position} ({joints.get(position, '?')}) 0x{code:04X} {describe_error(code)}")
    text = (f"every slave in OP in {report.seconds:.2f} s (SYNC0 {master.sync0_ns / 1e6:g} ms, bring-up loop "
            f"{report.bringup_rate:g} Hz, {report.cycles} cycles)")
    if faulted:
        return failed(GROUP, "op", f"{text}, but drives in fault: {'; '.join(faulted)}",
                      "`prime decode error CODE`, then `prime reset` while `prime bringup --backends ec` runs")
    return passed(GROUP, "op", f"{text}; every drive out of fault")
