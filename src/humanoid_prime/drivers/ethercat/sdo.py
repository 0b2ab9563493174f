"""SDO access for tools, by backend name: ``soem`` (this process owns the NIC) or ``igh`` (an IgH master does).

Both give the same blocking ``sdo_read(position, index, sub_index) -> bytes`` and
``sdo_write(position, index, sub_index, data)``, safe to call from one thread per slave at once.
With ``soem`` the ring is brought up here first (mailbox traffic must wait until every slave is in OP and
process data flows), and the master's keeper runs the cycle, drives disabled, until the session ends.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Protocol

from humanoid_prime.config.robot import Robot
from humanoid_prime.drivers.ethercat.master import RingError, expected_ring
from humanoid_prime.errors import PrimeError

SDO_BACKENDS = ("soem", "igh")


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
        self.sdo.sdo_write(position, address[0], address[1], value.to_bytes(size, "little"))


def check_backend(name: str) -> str:
    if name not in SDO_BACKENDS:
        raise PrimeError(f"unknown sdo_backend {name!r}; use one of {', '.join(SDO_BACKENDS)}")
    return name


@contextmanager
def open_sdo(backend: str, robot: Robot, *, interface: str | None = None, update_rate: float = 50.0,
             bringup_rate: float = 1000.0, ready_timeout_s: float = 2.0) -> Iterator[SdoClient]:
    """An SDO client for ``robot``'s ring on ``backend``; the ring must match the hardware file."""
    hw = robot.hardware
    if check_backend(backend) == "igh":
        from humanoid_prime.drivers.ethercat.igh import IghSdo

        yield IghSdo(hw.ethercat.master)
        return
    from humanoid_prime.drivers.ethercat.soem_master import SoemMaster

    master = SoemMaster(interface or hw.ethercat.interface, update_rate=update_rate,
                        bringup_rate=bringup_rate)
    with master:
        master.start(expected_ring(hw.erob_slaves))
        master.exchange()  # process data flows; from here the master's keeper sends it every period
        deadline = time.monotonic() + ready_timeout_s
        while not master.sdo_ready:
            if time.monotonic() > deadline:
                raise RingError(f"process data does not flow on {master.interface} after bring-up "
                                f"(working counter {master.wkc}, expected {master.expected_wkc})")
            time.sleep(0.005)
        yield master
