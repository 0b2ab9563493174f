"""The way back: a slave's CoE mailbox worked by SOEM alone (``buses.ethercat.mailbox: soem``), as before Prime had
a mailbox layer of its own. A drive that Prime's layer cannot talk to still comes up this way, and the mismatch can
be reported rather than block the robot.

SOEM's transfers (``ecx_SDOread``/``ecx_SDOwrite`` through pysoem, the interpreter lock released) run one at a time
on the whole ring: pysoem pops errors from one list shared by every slave (``ecx_poperror``), and a transfer of one
slave would otherwise raise another's abort. What SOEM's mailbox is (and why Prime's is the default) is in
``mailbox.py``; SOEM neither counts nor names what it drops.
"""

from __future__ import annotations

import threading

import pysoem

from humanoid_prime.drivers.ethercat.errors import SdoError


class SoemMailbox:
    """SDO access to the slave at ring ``position`` through pysoem's slave ``slave``; ``lock`` is the ring's."""

    def __init__(self, slave: pysoem.CdefSlave, position: int, lock: threading.Lock) -> None:
        self.slave = slave
        self.position = position
        self.lock = lock

    def reset_counter(self) -> None:
        """SOEM keeps the counters of the mailbox it alone uses."""

    def download(self, index: int, sub: int, data: bytes, timeout_s: float) -> None:
        with self.lock:
            try:
                self.slave.sdo_write(index, sub, bytes(data), release_gil=True)
            except (pysoem.SdoError, pysoem.MailboxError, pysoem.PacketError, pysoem.WkcError) as exc:
                raise soem_sdo_error(self.position, index, sub, exc) from None

    def upload(self, index: int, sub: int, timeout_s: float) -> bytes:
        with self.lock:
            try:
                data: bytes = self.slave.sdo_read(index, sub, release_gil=True)
                return data
            except (pysoem.SdoError, pysoem.MailboxError, pysoem.PacketError, pysoem.WkcError) as exc:
                raise soem_sdo_error(self.position, index, sub, exc) from None


def soem_sdo_error(position: int, index: int, sub: int, exc: Exception) -> SdoError:
    """One of pysoem's transfer errors as an SdoError of the slave at ``position``."""
    if isinstance(exc, pysoem.SdoError):
        return SdoError(position, index, sub, f"aborted with 0x{exc.abort_code:08X} ({exc.desc})", exc.abort_code)
    return SdoError(position, index, sub, describe_soem_error(exc))


def describe_soem_error(exc: BaseException) -> str:
    """One of pysoem's errors in words."""
    if isinstance(exc, pysoem.SdoError):
        return f"0x{exc.index:04X}:{exc.subindex:02X} aborted with 0x{exc.abort_code:08X} ({exc.desc})"
    if isinstance(exc, pysoem.MailboxError):
        return f"mailbox error {exc.error_code} ({exc.desc})"
    if isinstance(exc, pysoem.PacketError):
        return f"unexpected mailbox reply (SOEM's packet error {exc.error_code})"
    if isinstance(exc, pysoem.WkcError):
        return "no reply (working counter 0)"
    if isinstance(exc, SdoError):
        return str(exc)
    if str(exc) == "unexpected error":  # what pysoem calls an error it has no class for (an emergency among them)
        return "an error pysoem does not name (an emergency among them)"
    return str(exc) or type(exc).__name__
