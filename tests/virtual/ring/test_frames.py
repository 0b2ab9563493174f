"""EtherCAT frame layout: what SOEM puts on the wire, byte for byte."""

from __future__ import annotations

import pytest

from humanoid_prime.drivers.ethercat.wire import Command
from humanoid_prime.virtual.ring.frames import Datagram, FrameError, build_frame, iter_datagrams, parse_frame

# A frame as SOEM sends it for ecx_BRD(port, 0x0000, ECT_REG_TYPE, 2, ...): broadcast destination,
# source 01:01:01:01:01:01, EtherType 88A4, EtherCAT header 0x100E (type 1, 14 bytes), BRD index 5.
SOEM_BRD = bytes.fromhex(
    "ffffffffffff" "010101010101" "88a4"
    "0e10"
    "07" "05" "0000" "0000" "0200" "0000"
    "0000"
    "0000"
)


def test_soem_broadcast_read_parses_to_one_brd_datagram():
    (datagram,) = parse_frame(SOEM_BRD)
    assert datagram == Datagram(Command.BRD, b"\x00\x00", index=5, adp=0, ado=0, wkc=0, irq=0)


def test_built_frame_matches_soem_bytes():
    assert build_frame([Datagram(Command.BRD, b"\x00\x00", index=5)]) == SOEM_BRD


def test_more_follows_bit_is_set_on_all_but_the_last_datagram():
    frame = build_frame([Datagram.logical(Command.LRW, 0x10, bytes(4)),
                         Datagram(Command.FRMW, bytes(8), adp=0x1001, ado=0x0910)])
    first_length_field = int.from_bytes(frame[16 + 6:16 + 8], "little")
    second_offset = 16 + 10 + 4 + 2
    second_length_field = int.from_bytes(frame[second_offset + 6:second_offset + 8], "little")
    assert first_length_field == 0x8004
    assert second_length_field == 0x0008


def test_iter_datagrams_yields_command_offset_and_length():
    frame = build_frame([Datagram.logical(Command.LRW, 0x10, bytes(4)),
                         Datagram(Command.FRMW, bytes(8), adp=0x1001, ado=0x0910)])
    assert list(iter_datagrams(frame)) == [(Command.LRW, 16, 4), (Command.FRMW, 32, 8)]


def test_logical_address_splits_into_adp_low_and_ado_high():
    datagram = Datagram.logical(Command.LRW, 0x00020010, b"")
    assert (datagram.adp, datagram.ado, datagram.address) == (0x0010, 0x0002, 0x00020010)


def test_header_announcing_more_bytes_than_the_frame_holds_is_refused():
    broken = bytearray(SOEM_BRD)
    broken[14] = 0x40  # EtherCAT header now announces 64 bytes
    with pytest.raises(FrameError, match="announces 64 bytes"):
        list(iter_datagrams(broken))


def test_datagram_overrunning_the_frame_is_refused():
    broken = bytearray(SOEM_BRD)
    broken[16 + 6] = 0x20  # data length 32 in a 14-byte frame body
    with pytest.raises(FrameError, match="overruns"):
        list(iter_datagrams(broken))


def test_other_ethertype_is_refused():
    other = bytearray(SOEM_BRD)
    other[12:14] = b"\x08\x00"
    with pytest.raises(FrameError, match="not EtherCAT"):
        list(iter_datagrams(other))
