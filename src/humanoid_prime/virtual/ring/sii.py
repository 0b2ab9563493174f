"""The slave information interface (SII) EEPROM image of an emulated slave (ETG.2010 layout).

What SOEM reads from it (ethercatconfig.c, ethercatmain.c of the SOEM bundled with pysoem 1.1.13):

- words 0x08/0x0A/0x0C/0x0E: vendor id, product code, revision, serial number (u32 each);
- word 0x18: receive (master -> slave) mailbox offset and size; word 0x1A: send mailbox offset and
  size; word 0x1C: mailbox protocols (bit 2 = CoE);
- categories from word 0x40 on, each ``type u16, length u16 (words), data``; 0xFFFF ends the list:
  Strings (10, string 1 becomes the slave name), General (30; data byte 5 is the CoE details SOEM
  checks for complete access, byte 11 bit 1 would forbid LRW), FMMU (40), SyncManager (41, 8 bytes per
  SM: start, length, control, status, enable, type) and TxPDO/RxPDO (50/51). SOEM uses the SII PDO
  categories only when CoE yields no mapping; the emulated drives answer 0x1C12/0x1C13 over CoE.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

from humanoid_prime.drivers.erob.objects import PdoEntry
from humanoid_prime.drivers.ethercat.wire import (
    COE_DETAIL_PDO_ASSIGN,
    COE_DETAIL_PDO_CONFIG,
    COE_DETAIL_SDO,
    COE_DETAIL_SDO_INFO,
    MAILBOX_PROTOCOL_COE,
    SII_WORD_CATEGORIES,
    SII_WORD_MAILBOX,
    SII_WORD_SIZE,
    SII_WORD_VENDOR,
)

CATEGORY_STRINGS = 10
CATEGORY_GENERAL = 30
CATEGORY_FMMU = 40
CATEGORY_SYNC_MANAGER = 41
CATEGORY_TXPDO = 50
CATEGORY_RXPDO = 51
CATEGORY_END = 0xFFFF

SM_TYPE_MAILBOX_OUT = 1  # master -> slave
SM_TYPE_MAILBOX_IN = 2  # slave -> master
SM_TYPE_OUTPUTS = 3
SM_TYPE_INPUTS = 4
FMMU_OUTPUTS = 1
FMMU_INPUTS = 2
FMMU_MAILBOX_STATE = 3

IMAGE_SIZE = 2048  # bytes: a 16 kbit EEPROM

# CoE data type codes for the struct formats used in PDO entries.
DATA_TYPE_CODES = {"b": 0x0002, "h": 0x0003, "i": 0x0004, "B": 0x0005, "H": 0x0006, "I": 0x0007}


@dataclass(frozen=True)
class SyncManagerLayout:
    """One SyncManager as the SII describes it and as the slave expects the master to program it."""

    start: int
    length: int
    control: int
    sm_type: int


@dataclass(frozen=True)
class SiiContent:
    vendor_id: int
    product_code: int
    revision: int
    serial: int
    name: str
    group: str
    order: str
    sync_managers: tuple[SyncManagerLayout, ...]
    rx_pdo_index: int
    rx_pdo: tuple[PdoEntry, ...]
    tx_pdo_index: int
    tx_pdo: tuple[PdoEntry, ...]
    coe_details: int = COE_DETAIL_SDO | COE_DETAIL_SDO_INFO | COE_DETAIL_PDO_ASSIGN | COE_DETAIL_PDO_CONFIG


def crc8(data: bytes) -> int:
    """The SII header checksum: CRC-8, polynomial 0x07, initial value 0xFF, over words 0..6."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\x00"
    return struct.pack("<HH", kind, len(data) // 2) + data


def _strings(strings: Sequence[str]) -> bytes:
    out = bytearray([len(strings)])
    for text in strings:
        raw = text.encode("ascii")
        out += bytes([len(raw)]) + raw
    return bytes(out)


def _general(coe_details: int) -> bytes:
    general = bytearray(32)
    general[0] = 2  # group: string 2
    general[1] = 0  # no image
    general[2] = 3  # order: string 3
    general[3] = 1  # name: string 1
    general[5] = coe_details
    general[14] = 2  # group index repeated (ETG.2010 compatibility field)
    struct.pack_into("<H", general, 16, 0x0011)  # physical ports 0 and 1: MII
    return bytes(general)


def _pdo(index: int, sm: int, entries: Sequence[PdoEntry]) -> bytes:
    out = bytearray(struct.pack("<HBBBBH", index, len(entries), sm, 0, 0, 0))
    for e in entries:
        out += struct.pack("<HBBBBH", e.index, e.sub_index, 0, DATA_TYPE_CODES[e.fmt], e.bits, 0)
    return bytes(out)


def build_image(content: SiiContent, *, alias: int = 0) -> bytes:
    """The EEPROM image (IMAGE_SIZE bytes, unused space 0xFF) describing ``content``."""
    header = bytearray(0x80)
    struct.pack_into("<HHHHH", header, 0, 0x0C05, 0x0000, 0x0000, 0x0000, alias)
    struct.pack_into("<H", header, 14, crc8(bytes(header[:14])))
    struct.pack_into("<IIII", header, 2 * SII_WORD_VENDOR, content.vendor_id, content.product_code, content.revision,
                     content.serial)
    mailbox_out = next(s for s in content.sync_managers if s.sm_type == SM_TYPE_MAILBOX_OUT)
    mailbox_in = next(s for s in content.sync_managers if s.sm_type == SM_TYPE_MAILBOX_IN)
    struct.pack_into("<HHHHH", header, 2 * SII_WORD_MAILBOX, mailbox_out.start, mailbox_out.length, mailbox_in.start,
                     mailbox_in.length, MAILBOX_PROTOCOL_COE)
    struct.pack_into("<HH", header, 2 * SII_WORD_SIZE, IMAGE_SIZE * 8 // 1024 - 1, 1)  # size in kbit - 1; version 1

    sm_data = b"".join(struct.pack("<HHBBBB", s.start, s.length, s.control, 0, 1, s.sm_type)
                       for s in content.sync_managers)
    outputs_sm = next(i for i, s in enumerate(content.sync_managers) if s.sm_type == SM_TYPE_OUTPUTS)
    inputs_sm = next(i for i, s in enumerate(content.sync_managers) if s.sm_type == SM_TYPE_INPUTS)
    body = b"".join((
        _category(CATEGORY_STRINGS, _strings((content.name, content.group, content.order))),
        _category(CATEGORY_GENERAL, _general(content.coe_details)),
        _category(CATEGORY_FMMU, bytes((FMMU_OUTPUTS, FMMU_INPUTS, FMMU_MAILBOX_STATE, 0xFF))),
        _category(CATEGORY_SYNC_MANAGER, sm_data),
        _category(CATEGORY_TXPDO, _pdo(content.tx_pdo_index, inputs_sm, content.tx_pdo)),
        _category(CATEGORY_RXPDO, _pdo(content.rx_pdo_index, outputs_sm, content.rx_pdo)),
        struct.pack("<H", CATEGORY_END),
    ))
    image = bytes(header) + body
    if len(image) > IMAGE_SIZE:
        raise ValueError(f"SII content needs {len(image)} bytes, more than the {IMAGE_SIZE}-byte EEPROM")
    return image + b"\xff" * (IMAGE_SIZE - len(image))


def find_category(image: bytes, kind: int) -> bytes | None:
    """The data of the first category of ``kind``, walking the list as SOEM's ecx_siifind does."""
    address = SII_WORD_CATEGORIES * 2
    while address + 4 <= len(image):
        found, words = struct.unpack_from("<HH", image, address)
        if found == CATEGORY_END:
            return None
        if found == kind:
            return image[address + 4:address + 4 + words * 2]
        address += 4 + words * 2
    return None
