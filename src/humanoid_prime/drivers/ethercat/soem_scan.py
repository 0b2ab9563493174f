"""SOEM's ring scan, checked: SOEM opened on the NIC with its assumptions checked (``soem_contract.py``), its scan
repeated while it finds fewer slaves than answer a broadcast read of Prime's own (its frames came back after its 2 ms
frame timeout: a busy host or a slow ring), and each slave's identity as SOEM read it from the SII compared with the
SII itself, read over Prime's frames, where it looks like a failed read (a slow EEPROM) or where it differs from the
scan before.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import pysoem

from humanoid_prime.drivers.ethercat.errors import RingError
from humanoid_prime.drivers.ethercat.link import Wire
from humanoid_prime.drivers.ethercat.registers import NoReply, RingRegisters
from humanoid_prime.drivers.ethercat.soem_contract import FrameWatch, check_indices, check_version

SCAN_ATTEMPTS = 3  # ring scans when SOEM finds fewer slaves than answer our own broadcast read, or misreads an SII
SCAN_PATIENCE_S = 0.5  # how long our broadcast read waits for a ring that answers late
UNREAD = (0, 0xFFFFFFFF)  # what an SII read that failed leaves for a vendor id or product code


@dataclass(frozen=True)
class Identity:
    vendor: int
    product: int
    revision: int

    def __str__(self) -> str:
        return f"vendor 0x{self.vendor:08X} product 0x{self.product:08X} revision 0x{self.revision:08X}"


def soem_identity(slave: pysoem.CdefSlave) -> Identity:
    return Identity(slave.man, slave.id, slave.rev)


class SoemScan:
    """Scans the ring on ``interface`` with SOEM. ``wire(interface, indices)`` opens a wire of Prime's, ``watch``
    a frame watch on the NIC, ``on_sent`` is told of every frame of Prime's; ``reasons`` collects why scans were
    repeated."""

    def __init__(self, interface: str, *, wire: Callable[[str, range], Wire], watch: Callable[[str], FrameWatch],
                 sdo_timeout_s: float, clock: Callable[[], float] = time.monotonic,
                 on_sent: Callable[[], None] | None = None) -> None:
        self.interface = interface
        self.on_sent = on_sent
        self.wire = wire
        self.watch = watch
        self.sdo_timeout_s = sdo_timeout_s
        self.clock = clock
        self.reasons: list[str] = []

    def open(self) -> pysoem.Master:
        """SOEM on the NIC, its version checked."""
        try:
            socket.if_nametoindex(self.interface)
        except OSError:
            raise RingError(f"no network interface {self.interface!r} (buses.ethercat.interface in "
                            "prime_hardware.yaml); list them with `ip link` or pass --interface") from None
        problem = check_version(pysoem.__version__)
        if problem is not None:
            raise RingError(f"refusing the EtherCAT ring on {self.interface}: {problem}")
        m = pysoem.Master()
        try:
            m.open(self.interface)
        except ConnectionError:
            raise RingError(f"cannot open {self.interface!r} for EtherCAT: SOEM needs a raw socket, so run as root "
                            "or grant CAP_NET_RAW") from None
        m.sdo_read_timeout = m.sdo_write_timeout = round(self.sdo_timeout_s * 1e6)
        return m

    def scan(self, before: Sequence[Identity] | None = None) -> tuple[pysoem.Master, RingRegisters]:
        """SOEM opened and its ring scan done, with registers of Prime's over the slaves it found; ``before``: the
        identities a scan earlier found, which this one must find again."""
        for attempt in range(1, SCAN_ATTEMPTS + 1):
            m = self.open()
            watch = self.watch(self.interface)
            try:
                found = m.config_init()
                sent = watch.indices()
                problem = check_indices(sent) if sent or found <= 0 else (
                    "the NIC showed none of the frames of SOEM's ring scan, so the split of frame indices between "
                    "SOEM and Prime could not be checked")
            finally:
                watch.close()
            answered, waited = self._count()  # its reply reaches SOEM's socket too, which SOEM's next read drops
            if problem is not None:
                m.close()
                raise RingError(f"refusing the EtherCAT ring on {self.interface}: {problem}")
            if not answered:
                m.close()
                raise RingError(f"no EtherCAT slave answered on {self.interface} (a broadcast read waited "
                                f"{SCAN_PATIENCE_S * 1e3:g} ms): check the cable and the drives' power, and that no "
                                "other master (IgH) owns this NIC")
            why = None
            if found <= 0 or found < answered:
                why = (f"SOEM found {max(found, 0)} slaves, {answered} answered a broadcast read after "
                       f"{waited * 1e3:.1f} ms")
            registers = None
            if why is None:
                registers = RingRegisters(lambda indices: self.wire(self.interface, indices), len(m.slaves),
                                          clock=self.clock, on_sent=self.on_sent)
                why = self._misread(m.slaves, registers, before)
                if why is None and before is not None:
                    changed = changes(before, [soem_identity(slave) for slave in m.slaves])
                    if changed:  # its SII says so too: another ring
                        registers.close()
                        close_soem(m)
                        raise RingError(f"the EtherCAT ring on {self.interface} changed while it was being configured "
                                        f"again: {changed}")
            if why is None and registers is not None:
                return m, registers
            if registers is not None:
                registers.close()
            close_soem(m)
            self.reasons.append(f"scan {attempt}: {why}")
        raise RingError(f"SOEM's scan of the EtherCAT ring on {self.interface} did not find it in {SCAN_ATTEMPTS} "
                        "tries (its frames came back later than its 2 ms frame timeout, or its SII reads failed: a "
                        "busy host, a slow ring or a slow EEPROM): " + "; ".join(self.reasons))

    def _count(self) -> tuple[int, float]:
        """(slaves that answer a broadcast read of ours, how long it took; 0 when none came back in
        ``SCAN_PATIENCE_S``)."""
        probe = RingRegisters(lambda indices: self.wire(self.interface, indices), 1, clock=self.clock)
        try:
            began = self.clock()
            answered = probe.count(SCAN_PATIENCE_S)
            return answered or 0, self.clock() - began
        finally:
            probe.close()

    def _misread(self, slaves: Sequence[pysoem.CdefSlave], registers: RingRegisters,
                 before: Sequence[Identity] | None = None) -> str | None:
        """Why the identities SOEM read cannot be taken (None: they can): a slave at another station address, or one
        whose SII, read again over our frames, holds another identity. Read again: the identities that look like a
        failed read, and those that differ from ``before``."""
        wrong = registers.check_stations()
        if wrong:
            return f"ring {', '.join(map(str, wrong))} do not answer at the station address SOEM gave them"
        found = [soem_identity(slave) for slave in slaves]
        suspect = [k for k, identity in enumerate(found) if identity.vendor in UNREAD or identity.product in UNREAD
                   or (before is not None and (k >= len(before) or identity != before[k]))]
        for k in suspect:
            try:
                own = Identity(*registers.sii_identity(k))
            except NoReply as exc:
                return f"ring {k}: SOEM read {found[k]} and its SII could not be read again ({exc.what})"
            if own != found[k]:
                return f"ring {k}: SOEM read {found[k]} from the SII, which holds {own} (a failed or slow EEPROM read)"
        return None


def changes(before: Sequence[Identity], now: Sequence[Identity]) -> str:
    """What differs between two scans of a ring, in words ('' when nothing does)."""
    words = [f"ring {k} was {before[k]}, now {now[k]}" for k in range(min(len(before), len(now)))
             if before[k] != now[k]]
    if len(before) != len(now):
        words.append(f"{len(before)} slaves before, {len(now)} now")
    return "; ".join(words)


def close_soem(m: pysoem.Master, slaves: bool = True) -> None:
    """SOEM's slaves back to INIT (where it found any) and its NIC released."""
    try:
        if slaves and len(m.slaves):
            m.state = pysoem.INIT_STATE
            m.write_state()
    finally:
        m.close()
