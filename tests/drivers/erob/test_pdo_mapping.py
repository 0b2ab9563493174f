"""The PRE-OP mapping writes: assignment and mapping cleared, entries written, counts and assignment restored."""

from __future__ import annotations

import struct

from humanoid_prime.drivers.erob.objects import (
    MAPPING_WRITES,
    RXPDO,
    RXPDO_ASSIGN,
    RXPDO_MAP,
    RXPDO_STRUCT,
    TXPDO,
    TXPDO_STRUCT,
    pdo_mapping_writes,
)


def u32(value: int) -> bytes:
    return struct.pack("<I", value)


def test_the_rxpdo_is_mapped_in_the_order_a_drive_accepts():
    assert pdo_mapping_writes(RXPDO_ASSIGN, RXPDO_MAP, RXPDO) == [
        (0x1C12, 0, b"\x00"),
        (0x1600, 0, b"\x00"),
        (0x1600, 1, u32(0x60400010)),  # controlword u16
        (0x1600, 2, u32(0x607A0020)),  # target position i32
        (0x1600, 3, u32(0x60B10020)),  # velocity offset i32
        (0x1600, 4, u32(0x60B20010)),  # torque offset i16
        (0x1600, 5, u32(0x60600008)),  # mode of operation i8
        (0x1600, 6, u32(0x00000008)),  # pad byte
        (0x1600, 0, b"\x06"),
        (0x1C12, 1, struct.pack("<H", 0x1600)),
        (0x1C12, 0, b"\x01"),
    ]


def test_the_txpdo_maps_statusword_position_velocity_torque_error_and_mode_display():
    tx = [w for w in MAPPING_WRITES if w[0] == 0x1A00 and w[1] != 0]
    assert [struct.unpack("<I", data)[0] for _, _, data in tx] == [
        0x60410010, 0x60640020, 0x606C0020, 0x60770010, 0x603F0010, 0x60610008, 0x00000008]
    assert len(TXPDO) == 7


def test_both_pdos_are_padded_to_an_even_length():
    assert (RXPDO_STRUCT.size, TXPDO_STRUCT.size) == (14, 16)


def test_every_mapping_write_is_expedited():
    assert all(len(data) <= 4 for _, _, data in MAPPING_WRITES)
