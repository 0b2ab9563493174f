"""SDO access by ring position: the one interface every backend offers (a master, the IgH adapter, a running
prime's control socket), and objects written with the size the drive itself reports.

A drive may not say an object's size: an expedited upload without a size indication carries all four bytes
(CiA 301 allows it), so a u16 reads as 4 bytes. A write of that size to a CoE stack that enforces sizes is aborted
with a length code (0x0607001x); it is then written again in the next narrower size the value fits, and that size
is kept (``write_fitting``)."""

from __future__ import annotations

import struct
from typing import Protocol

from humanoid_prime.drivers.erob.objects import ERROR_CODE, ERROR_HISTORY
from humanoid_prime.drivers.ethercat.errors import SdoError
from humanoid_prime.drivers.ethercat.wire import LENGTH_ABORTS
from humanoid_prime.errors import PrimeError

SIZES = (1, 2, 4)  # bytes of the integer objects a CoE stack holds


class SdoClient(Protocol):
    """Blocking SDO access by ring position (a master, the IgH adapter, or a running prime's control socket)."""

    def sdo_read(self, position: int, index: int, sub_index: int) -> bytes: ...

    def sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None: ...


class SizedSdo:
    """Unsigned object values through any SdoClient, written with the size the drive itself reports.

    Drives disagree on the width of the same object (the eRob EDS declares the loop gains UNSIGNED16, a
    public host reads them as u32), and a CoE stack that enforces sizes aborts a write of another length.
    So each object is uploaded once per slave and its size remembered; writes use exactly that size.
    Thread-safe for one thread per slave.
    """

    def __init__(self, sdo: SdoClient) -> None:
        self.sdo = sdo
        self.sizes: dict[tuple[int, int, int], int] = {}

    def read(self, position: int, address: tuple[int, int]) -> int:
        """The object's value (little-endian, unsigned); learns its size on the way."""
        index, sub = address
        data = self.sdo.sdo_read(position, index, sub)
        if not 1 <= len(data) <= 8:
            raise PrimeError(f"ring {position}: 0x{index:04X}:{sub:02X} answered {len(data)} bytes; expected 1 to 8")
        self.sizes[(position, index, sub)] = len(data)
        return int.from_bytes(data, "little")

    def size(self, position: int, address: tuple[int, int]) -> int:
        """Bytes the drive holds the object in (uploaded once, then remembered)."""
        key = (position, *address)
        if key not in self.sizes:
            try:
                self.read(position, address)
            except PrimeError as exc:
                raise PrimeError(f"ring {position}: cannot learn the size of 0x{address[0]:04X}:{address[1]:02X} "
                                 f"before writing it ({exc}); nothing was written") from None
        return self.sizes[key]

    def write(self, position: int, address: tuple[int, int], value: int) -> None:
        """Download ``value`` with the object's own size; refused before the bus if it does not fit."""
        size = self.size(position, address)
        if not 0 <= value < 1 << (8 * size):
            raise PrimeError(f"ring {position}: {value} does not fit 0x{address[0]:04X}:{address[1]:02X}, "
                             f"which this drive holds in {size} bytes (0..{(1 << (8 * size)) - 1})")
        self.sizes[(position, *address)] = write_fitting(self.sdo, position, address, value, size)


def write_fitting(sdo: SdoClient, position: int, address: tuple[int, int], value: int, size: int,
                  signed: bool = False) -> int:
    """Download ``value`` in ``size`` bytes; if the drive aborts it for its length, in each narrower size the value
    fits, then each wider; returns the size the drive took (the first abort of another kind, or the last, is
    raised)."""
    index, sub = address
    refused: SdoError | None = None
    for width in [size, *(n for n in reversed(SIZES) if n < size), *(n for n in SIZES if n > size)]:
        try:
            data = value.to_bytes(width, "little", signed=signed)
        except OverflowError:
            continue
        try:
            sdo.sdo_write(position, index, sub, data)
            return width
        except SdoError as exc:
            if exc.abort_code not in LENGTH_ABORTS:
                raise
            refused = exc
    if refused is not None:
        raise refused
    raise PrimeError(f"ring {position}: {value} does not fit 0x{index:04X}:{sub:02X} in {size} bytes")


def read_live_error(sdo: SdoClient, position: int) -> int:
    """The drive's current error code (0x603F), through any SDO client."""
    code: int = struct.unpack("<H", sdo.sdo_read(position, ERROR_CODE, 0)[:2].ljust(2, b"\0"))[0]
    return code


def read_error_history(sdo: SdoClient, position: int) -> list[int]:
    """The drive's stored error codes (0x1003, newest first; the low 16 bits of each entry)."""
    count = sdo.sdo_read(position, ERROR_HISTORY, 0)[0]
    codes = []
    for sub in range(1, count + 1):
        raw = sdo.sdo_read(position, ERROR_HISTORY, sub)[:4].ljust(4, b"\0")
        codes.append(struct.unpack("<I", raw)[0] & 0xFFFF)
    return codes
