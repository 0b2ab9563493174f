"""Prime's PDO mapping on each drive, what SOEM laid out from it, and the ESC setup a reconfiguration writes back.

A drive powers up with ZeroErr's own mapping (``POWER_UP_RXPDO``), so SOEM's PRE-OP -> SAFE-OP hook
(``PdoMapping.hook``) writes Prime's over SDO every bring-up: 0x1C12/0x1C13 cleared, 0x1600/0x1A00 written, the
assignment restored (``MAPPING_WRITES``), then reads the drive's rated torque (0x6076). SOEM's ``config_map``
then reads the mapping back through its own mailbox and sizes the process image from it (``ecx_readPDOmap``).

That read-back takes a late reply for its answer (``mailbox.py``): a reply to the write of 0x1A00:05 read as the
answer to the read of 0x1A00:05 counts that 16-bit entry as 0 bits. So when SOEM's sizes are not Prime's,
``PdoMapping.check`` reads the mapping back itself and says which it was: the drive holds Prime's mapping (SOEM
miscounted it, to be configured again) or another one (the drive did not take it).
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from humanoid_prime.drivers.erob.objects import (
    MAPPING_WRITES,
    RATED_TORQUE,
    RXPDO,
    RXPDO_ASSIGN,
    RXPDO_STRUCT,
    TXPDO,
    TXPDO_ASSIGN,
    TXPDO_STRUCT,
)
from humanoid_prime.drivers.ethercat.errors import SdoError, SdoTimeout
from humanoid_prime.drivers.ethercat.mailbox import SdoMailbox
from humanoid_prime.drivers.ethercat.registers import NoReply, RingRegisters
from humanoid_prime.drivers.ethercat.wire import (
    ESC_FEATURE_DC,
    FMMU_SIZE,
    REG_DC_DELAY,
    REG_ESC_FEATURES,
    REG_FMMU,
    REG_FMMU_SM_COUNT,
    REG_SM,
    SM_ENABLE,
    SM_LAYOUT,
    SM_MODE_MAILBOX,
    SM_MODE_MASK,
    SM_REPEAT,
    SM_SIZE,
)

SOEM_MAXSM, SOEM_MAXFMMU = 8, 4  # what SOEM configures at most (EC_MAXSM, EC_MAXFMMU in ethercatmain.h)
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
EXPECTED_BYTES = (RXPDO_STRUCT.size, TXPDO_STRUCT.size)


@dataclass(frozen=True)
class EscSetup:
    """A slave's SyncManager and FMMU registers as SOEM programmed them at bring-up: (address, bytes) each, in the
    order ``ecx_reconfig_slave`` writes them. Only SOEM's own fields: the SyncManager's status and PDI-control bytes,
    which the ESC sets, go back as 0, as SOEM writes them, and its activate byte without a mailbox repeat request."""

    sync_managers: tuple[tuple[int, bytes], ...]
    fmmus: tuple[tuple[int, bytes], ...]
    dc: bool = False  # the ESC has a distributed clock
    dc_delay: int = 0  # its propagation delay from the reference clock (0x0928), as ``config_dc`` measured it


def read_esc_setup(registers: RingRegisters, k: int) -> EscSetup:
    """Ring ``k``'s SyncManagers (those with a start address), FMMUs (those SOEM set) and distributed clock, each
    read until two reads agree; NoReply when they would not."""
    fmmu_count, sm_count = registers.read_agreed(k, REG_FMMU_SM_COUNT, 2)
    sms = registers.read_agreed(k, REG_SM, SM_SIZE * min(sm_count, SOEM_MAXSM))
    fmmus = registers.read_agreed(k, REG_FMMU, FMMU_SIZE * min(fmmu_count, SOEM_MAXFMMU))
    dc = bool(_U16.unpack(registers.read_agreed(k, REG_ESC_FEATURES, 2))[0] & ESC_FEATURE_DC)
    delay = _U32.unpack(registers.read_agreed(k, REG_DC_DELAY, 4))[0] if dc else 0
    sync_managers = []
    for n in range(len(sms) // SM_SIZE):
        start, length, control, _status, activate, _pdi = SM_LAYOUT.unpack_from(sms, SM_SIZE * n)
        if start:
            sync_managers.append((REG_SM + SM_SIZE * n,
                                  SM_LAYOUT.pack(start, length, control, 0, activate & ~SM_REPEAT & 0xFF, 0)))
    return EscSetup(sync_managers=tuple(sync_managers),
                    fmmus=tuple((REG_FMMU + FMMU_SIZE * n, fmmu) for n in range(len(fmmus) // FMMU_SIZE)
                                if any(fmmu := fmmus[FMMU_SIZE * n:FMMU_SIZE * (n + 1)])),
                    dc=dc, dc_delay=delay)


def mailbox_sync_managers(registers: RingRegisters, k: int) -> tuple[int, int, int, int]:
    """(write start, write size, read start, read size) of slave ``k``'s mailboxes, from SM0 and SM1."""
    sms = registers.read_agreed(k, REG_SM, 2 * SM_SIZE)
    out_start, out_size, out_control, _s, out_active, _p = SM_LAYOUT.unpack_from(sms, 0)
    in_start, in_size, in_control, _s, in_active, _p = SM_LAYOUT.unpack_from(sms, SM_SIZE)
    if not (out_control & SM_MODE_MASK == SM_MODE_MAILBOX and in_control & SM_MODE_MASK == SM_MODE_MAILBOX
            and out_active & SM_ENABLE and in_active & SM_ENABLE and out_size >= 16 and in_size >= 16):
        raise NoReply(f"ring {k}: SM0/SM1 hold no mailbox (control 0x{out_control:02X}/0x{in_control:02X})")
    return out_start, out_size, in_start, in_size


class PdoMapping:
    """The PRE-OP work on each drive, through its mailbox (``mailboxes[k]``), each transfer with ``timeout_s``.
    ``on_rated_torque(k, raw or None, problem)`` gets what 0x6076 answered."""

    def __init__(self, mailboxes: Sequence[SdoMailbox], timeout_s: float,
                 on_rated_torque: Callable[[int, bytes | None, str], None]) -> None:
        self.mailboxes = mailboxes
        self.timeout_s = timeout_s
        self.on_rated_torque = on_rated_torque
        self.problems: dict[int, str] = {}  # ring position -> why its mapping failed (SOEM's hook can raise no text)

    def hook(self, k: int) -> None:
        """SOEM's PRE-OP -> SAFE-OP hook for ring ``k``: Prime's mapping, then the rated torque. Raises SdoError
        (kept in ``problems``) when a mapping write fails."""
        mailbox = self.mailboxes[k]
        try:
            for index, sub_index, data in MAPPING_WRITES:
                mailbox.download(index, sub_index, data, self.timeout_s)
        except SdoError as exc:
            verdict = ("the drive refused it" if exc.abort_code is not None else
                       exc.verdict if isinstance(exc, SdoTimeout) else "the drive did not answer")
            self.problems[k] = (f"ring {k}: PDO mapping write 0x{exc.index:04X}:{exc.sub_index:02X}: {exc.problem} "
                                f"({verdict})")
            raise
        self.problems.pop(k, None)
        mailbox.reset_counter()  # the last request before SOEM reads the mapping back through this mailbox
        try:
            self.on_rated_torque(k, mailbox.upload(RATED_TORQUE, 0, self.timeout_s), "")
        except SdoError as exc:
            self.on_rated_torque(k, None, exc.problem)

    def held(self, k: int) -> tuple[list[int], list[int]]:
        """The mapping entries (index:sub:bits) ring ``k`` holds in the PDOs its 0x1C12/0x1C13 assign."""
        mailbox = self.mailboxes[k]

        def entries(assign: int) -> list[int]:
            out = []
            for a in range(1, mailbox.upload(assign, 0, self.timeout_s)[0] + 1):
                pdo = _U16.unpack(mailbox.upload(assign, a, self.timeout_s)[:2])[0]
                for e in range(1, mailbox.upload(pdo, 0, self.timeout_s)[0] + 1):
                    out.append(_U32.unpack(mailbox.upload(pdo, e, self.timeout_s)[:4])[0])
            return out

        return entries(RXPDO_ASSIGN), entries(TXPDO_ASSIGN)

    def check(self, k: int, sizes: tuple[int, int]) -> str | None:
        """None when SOEM's (output, input) bytes of ring ``k`` are Prime's; otherwise what happened, in words,
        ending in whether the drive holds Prime's mapping (read back over our own mailbox)."""
        if sizes == EXPECTED_BYTES:
            return None
        text = (f"ring {k}: SOEM laid out {sizes[0]} output and {sizes[1]} input bytes, expected "
                f"{EXPECTED_BYTES[0]} and {EXPECTED_BYTES[1]} (drivers/erob/objects.py)")
        try:
            rx, tx = self.held(k)
        except SdoError as exc:
            return f"{text}; reading the drive's mapping back failed too: {exc.problem}"
        if (rx, tx) == ([e.mapping for e in RXPDO], [e.mapping for e in TXPDO]):
            return (f"{text}, but the drive holds Prime's mapping: SOEM's read-back of it took a reply that was not "
                    "its own (one that came late)")
        held = ", ".join(f"0x{m:08X}" for m in rx) + " / " + ", ".join(f"0x{m:08X}" for m in tx)
        return f"{text}; the drive holds {held} (RxPDO / TxPDO): it did not take Prime's mapping"
