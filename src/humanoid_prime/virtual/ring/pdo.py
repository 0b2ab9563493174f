"""The process data of one emulated eRob: the PDO mapping objects (0x1600/0x1A00, assigned by 0x1C12/0x1C13), which
the master may change in PRE-OP only and which are validated when their sub-index 0 is written, and the codecs that
carry the mapped objects between the SyncManager memory and the object dictionary from SAFE-OP on.

PRE-OP -> SAFE-OP needs SM2/SM3 matching the mapping (else AL status 0x001D/0x001E, ETG.1000.6).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

from humanoid_prime.drivers.erob import objects as obj
from humanoid_prime.drivers.ethercat.wire import (
    ABORT_DEVICE_STATE,
    ABORT_NOT_MAPPABLE,
    ABORT_PDO_LENGTH,
    ABORT_SUBINDEX_ZERO_FIRST,
    AL_CODE_INVALID_INPUT_CONFIG,
    AL_CODE_INVALID_OUTPUT_CONFIG,
    SM_DIRECTION_WRITE,
    SM_ENABLE,
    SM_MODE_MASK,
)
from humanoid_prime.virtual.ring.esc import MEMORY_SIZE, Esc
from humanoid_prime.virtual.ring.od import Entry, ObjectDictionary, SdoAbort

SM_OUTPUTS = 2
SM_INPUTS = 3
MAX_PDO_BYTES = 0x80
MAX_PDO_ENTRIES = 16


class PdoCodec:
    """Packs or unpacks one direction of process data between SM memory and OD entries."""

    def __init__(self, entries: list[Entry | None], paddings: list[int]) -> None:
        fmt = "<"
        self.entries: list[Entry] = []
        for entry, pad in zip(entries, paddings, strict=True):
            if entry is None:
                fmt += "x" * pad
            else:
                fmt += entry.fmt
                self.entries.append(entry)
        self.struct = struct.Struct(fmt)

    @property
    def size(self) -> int:
        return self.struct.size

    def unpack(self, memory: bytearray, address: int) -> None:
        for entry, value in zip(self.entries, self.struct.unpack_from(memory, address), strict=True):
            entry.value = value

    def pack(self, memory: bytearray, address: int) -> None:
        self.struct.pack_into(memory, address, *[e.value for e in self.entries])


@dataclass(frozen=True)
class ProcessData:
    """The codecs of both directions and where SM2 (outputs) and SM3 (inputs) put them."""

    rx: PdoCodec
    tx: PdoCodec
    outputs_at: int
    inputs_at: int


def compile_process_data(od: ObjectDictionary, esc: Esc) -> ProcessData | int:
    """The codecs from 0x1C12/0x1C13, checked against SM2/SM3; the AL status code that refuses SAFE-OP if they do
    not match."""
    try:
        rx = _codec(od, obj.RXPDO_ASSIGN)
        tx = _codec(od, obj.TXPDO_ASSIGN)
    except SdoAbort:
        return AL_CODE_INVALID_OUTPUT_CONFIG
    for sm, codec, code, write in ((SM_OUTPUTS, rx, AL_CODE_INVALID_OUTPUT_CONFIG, True),
                                   (SM_INPUTS, tx, AL_CODE_INVALID_INPUT_CONFIG, False)):
        start, length, control, activate = esc.sync_manager(sm)
        if codec.size == 0:
            continue
        if (length != codec.size or not activate & SM_ENABLE or control & SM_MODE_MASK != 0
                or bool(control & SM_DIRECTION_WRITE) != write or start + length > MEMORY_SIZE):
            return code
    return ProcessData(rx, tx, esc.sync_manager(SM_OUTPUTS)[0], esc.sync_manager(SM_INPUTS)[0])


def _codec(od: ObjectDictionary, assign_index: int) -> PdoCodec:
    entries: list[Entry | None] = []
    paddings: list[int] = []
    for i in range(1, int(od.value(assign_index, 0)) + 1):
        pdo = int(od.value(assign_index, i))
        for sub in range(1, int(od.value(pdo, 0)) + 1):
            mapping = int(od.value(pdo, sub))
            index, subindex, bits = mapping >> 16, (mapping >> 8) & 0xFF, mapping & 0xFF
            if index == 0:
                entries.append(None)
                paddings.append(bits // 8)
            else:
                entries.append(od.entry(index, subindex))
                paddings.append(0)
    return PdoCodec(entries, paddings)


def guard_pdo_objects(od: ObjectDictionary, in_pre_op: Callable[[], bool]) -> None:
    """The mapping and assignment objects writable only while ``in_pre_op()``, validated as a drive validates them."""
    for assign, pdo, direction in ((obj.RXPDO_ASSIGN, obj.RXPDO_MAP, "rx"), (obj.TXPDO_ASSIGN, obj.TXPDO_MAP, "tx")):
        for sub in range(0, MAX_PDO_ENTRIES + 1):
            od.entry(pdo, sub).on_write = _mapping_write(od, in_pre_op, pdo, sub, direction)
        od.entry(assign, 0).on_write = _assign_write(in_pre_op, 0, pdo)
        od.entry(assign, 1).on_write = _assign_write(in_pre_op, 1, pdo)


def _check_pre_op(in_pre_op: Callable[[], bool]) -> None:
    if not in_pre_op():
        raise SdoAbort(ABORT_DEVICE_STATE, "PDO mapping can only change in PRE-OP")


def _mapping_write(od: ObjectDictionary, in_pre_op: Callable[[], bool], pdo: int, sub: int,
                   direction: str) -> Callable[[Entry, int | str], None]:
    def hook(entry: Entry, value: int | str) -> None:
        _check_pre_op(in_pre_op)
        if sub != 0:
            if int(od.value(pdo, 0)) != 0:
                raise SdoAbort(ABORT_SUBINDEX_ZERO_FIRST)
            return
        if not 0 <= int(value) <= MAX_PDO_ENTRIES:
            raise SdoAbort(ABORT_PDO_LENGTH)
        total = 0
        for i in range(1, int(value) + 1):
            mapping = int(od.value(pdo, i))
            index, subindex, bits = mapping >> 16, (mapping >> 8) & 0xFF, mapping & 0xFF
            if bits % 8:
                raise SdoAbort(ABORT_NOT_MAPPABLE, f"0x{index:04X}:{subindex:02X} bit length {bits}")
            if index != 0:
                target = od.entry(index, subindex) if (index, subindex) in od else None
                if target is None or target.pdo != direction or target.bits != bits:
                    raise SdoAbort(ABORT_NOT_MAPPABLE, f"0x{index:04X}:{subindex:02X}")
            total += bits // 8
        if total > MAX_PDO_BYTES:
            raise SdoAbort(ABORT_PDO_LENGTH)
    return hook


def _assign_write(in_pre_op: Callable[[], bool], sub: int, pdo: int) -> Callable[[Entry, int | str], None]:
    def hook(entry: Entry, value: int | str) -> None:
        _check_pre_op(in_pre_op)
        if sub == 0 and int(value) > 1:
            raise SdoAbort(ABORT_PDO_LENGTH)
        if sub == 1 and int(value) != pdo:
            raise SdoAbort(ABORT_NOT_MAPPABLE, f"only 0x{pdo:04X} can be assigned")
    return hook
