"""EtherCAT frames and datagrams: a parser that yields datagram offsets, and a builder (the layout is
``drivers/ethercat/wire.py``'s).

Wire format (ETG.1000.4; what SOEM sends and expects back):

- Ethernet header, 14 bytes: destination MAC, source MAC, EtherType 0x88A4. SOEM sends to the broadcast
  address from 01:01:01:01:01:01 and ignores the MAC on receive.
- EtherCAT header, 2 bytes little-endian: bits 0-10 length of the datagrams that follow, bits 12-15 type
  (1 = EtherCAT commands).
- One or more datagrams, each: command u8, index u8, address u32 (ADP u16 + ADO u16, or one logical
  u32), length u16 (bits 0-10 data length, bit 14 circulating frame, bit 15 more datagrams follow),
  IRQ u16, data, working counter u16.

A slave changes a datagram only in place: its data, its working counter, and for auto-increment and
broadcast commands the ADP (each slave adds one). The reply therefore has the request's length.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass

from humanoid_prime.drivers.ethercat.wire import (
    BROADCAST_MAC,
    DATAGRAM_HEADER,
    DATAGRAM_HEADER_SIZE,
    ECAT_HEADER_SIZE,
    ETH_HEADER_SIZE,
    ETHERTYPE,
    FRAME_TYPE_COMMANDS,
    LENGTH_MASK,
    MASTER_MAC,
    MORE_FOLLOWS,
    WKC_SIZE,
    Command,
)

_U16 = struct.Struct("<H")
_ADDRESS = struct.Struct("<HH")
_ETHERTYPE_BYTES = struct.pack(">H", ETHERTYPE)


class FrameError(ValueError):
    """A frame that is not a well-formed EtherCAT frame (slaves forward nothing they cannot parse)."""


@dataclass
class Datagram:
    """One datagram, for building frames and reading replies (tests, tools). ``address`` is the logical
    address for LRD/LWR/LRW; otherwise ``adp``/``ado``."""

    command: Command
    data: bytes
    index: int = 0
    adp: int = 0
    ado: int = 0
    wkc: int = 0
    irq: int = 0

    @property
    def address(self) -> int:
        return (self.ado << 16) | self.adp

    @classmethod
    def logical(cls, command: Command, address: int, data: bytes, index: int = 0) -> Datagram:
        return cls(command, data, index=index, adp=address & 0xFFFF, ado=(address >> 16) & 0xFFFF)


def iter_datagrams(frame: bytes | bytearray | memoryview) -> Iterator[tuple[int, int, int]]:
    """Yield ``(command, offset, data_length)`` for each datagram of an Ethernet frame.

    ``offset`` points at the datagram header (command byte); its data starts at ``offset + 10`` and its
    working counter at ``offset + 10 + data_length``. Raises FrameError for a frame that is not EtherCAT
    or whose datagrams overrun it.
    """
    size = len(frame)
    if size < ETH_HEADER_SIZE + ECAT_HEADER_SIZE:
        raise FrameError(f"frame of {size} bytes is shorter than the Ethernet and EtherCAT headers")
    if frame[12:14] != _ETHERTYPE_BYTES:
        raise FrameError(f"EtherType 0x{frame[12]:02X}{frame[13]:02X} is not EtherCAT (0x{ETHERTYPE:04X})")
    header = _U16.unpack_from(frame, ETH_HEADER_SIZE)[0]
    if header >> 12 != FRAME_TYPE_COMMANDS:
        raise FrameError(f"EtherCAT frame type {header >> 12} is not 1 (commands)")
    end = ETH_HEADER_SIZE + ECAT_HEADER_SIZE + (header & LENGTH_MASK)
    if end > size:
        raise FrameError(f"EtherCAT header announces {header & LENGTH_MASK} bytes but the frame has {size}")
    offset = ETH_HEADER_SIZE + ECAT_HEADER_SIZE
    while True:
        if offset + DATAGRAM_HEADER_SIZE + WKC_SIZE > end:
            raise FrameError(f"datagram at byte {offset} overruns the frame")
        length_field = _U16.unpack_from(frame, offset + 6)[0]
        length = length_field & LENGTH_MASK
        if offset + DATAGRAM_HEADER_SIZE + length + WKC_SIZE > end:
            raise FrameError(f"datagram at byte {offset} with {length} data bytes overruns the frame")
        yield frame[offset], offset, length
        if not length_field & MORE_FOLLOWS:
            return
        offset += DATAGRAM_HEADER_SIZE + length + WKC_SIZE


def build_frame(datagrams: list[Datagram], *, source: bytes = MASTER_MAC,
                destination: bytes = BROADCAST_MAC) -> bytes:
    """An Ethernet frame carrying ``datagrams`` in order (the more-follows bit set on all but the last)."""
    body = bytearray()
    for i, d in enumerate(datagrams):
        length_field = len(d.data) | (MORE_FOLLOWS if i < len(datagrams) - 1 else 0)
        body += DATAGRAM_HEADER.pack(int(d.command), d.index, d.adp, d.ado, length_field, d.irq)
        body += d.data
        body += _U16.pack(d.wkc)
    header = _U16.pack((FRAME_TYPE_COMMANDS << 12) | len(body))
    return destination + source + _ETHERTYPE_BYTES + header + bytes(body)


def parse_frame(frame: bytes | bytearray) -> list[Datagram]:
    """All datagrams of a frame, copied out (for tests and tools; the ring works on offsets)."""
    out = []
    for command, offset, length in iter_datagrams(frame):
        index = frame[offset + 1]
        adp, ado = _ADDRESS.unpack_from(frame, offset + 2)
        irq = _U16.unpack_from(frame, offset + 8)[0]
        data_start = offset + DATAGRAM_HEADER_SIZE
        wkc = _U16.unpack_from(frame, data_start + length)[0]
        out.append(Datagram(Command(command), bytes(frame[data_start:data_start + length]), index=index,
                            adp=adp, ado=ado, wkc=wkc, irq=irq))
    return out
