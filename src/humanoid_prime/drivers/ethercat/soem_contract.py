"""What Prime's frames beside SOEM's rest on, checked when the ring is opened and kept while it runs
(docs/development.md, "One master layer beside SOEM"):

1. SOEM numbers its frames 0..EC_MAXBUF-1 (``ecx_getindex``, oshw/linux/nicdrv.c; EC_MAXBUF is 16 in the SOEM that
   pysoem 1.1.13 bundles, soem/ethercattype.h). Prime's frames carry ``FIRST_INDEX``..0xFF (``link.py``), so no reply
   of one is ever taken for the other's.
2. SOEM drops a frame whose index is none it waits for ("strange things happened", ``ecx_inframe``): a reply of
   Prime's in SOEM's socket is read and thrown away, never filed.
3. SOEM reads its socket only while it waits for a frame of its own, so Prime's replies queue there meanwhile (the
   kernel copies every EtherCAT frame to every packet socket on the NIC). A socket's queue (``rmem_default``,
   212992 bytes by default) holds about 90 frames at the ~2.3 KB a NIC driver allocates per received frame (167 of
   Prime's mailbox frames on a veth pair, measured); a reply of SOEM's arriving at a full queue is lost. So the master
   has SOEM read its socket (``QueueKeeper``) before ``QUEUE_LIMIT`` frames of Prime's can queue there.
4. SOEM touches a slave's mailbox only inside ``config_init``/``config_map`` (and ``recover``/``reconfig``, which Prime
   never calls): afterwards the mailbox is Prime's (or, with ``buses.ethercat.mailbox: soem``, SOEM's alone).

Checked at every opening: the pysoem installed is the version these facts were read from (``TESTED_PYSOEM``, pinned
in pyproject.toml), and every frame seen on the NIC during SOEM's ring scan carries an index below EC_MAXBUF. A
check that fails refuses the ring with one line.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Iterable
from typing import Protocol

from humanoid_prime.drivers.ethercat.link import FIRST_INDEX, frame_index
from humanoid_prime.drivers.ethercat.wire import ETHERTYPE

TESTED_PYSOEM = "1.1.13"
EC_MAXBUF = 16
QUEUE_LIMIT = 48  # frames of Prime's SOEM's socket may hold before SOEM is made to read it
WATCH_BUFFER = 4 << 20  # bytes a watch socket asks for, to see a whole ring scan
ETH_P_ALL = 0x0003  # linux/if_ether.h
ETHERTYPE_BYTES = ETHERTYPE.to_bytes(2, "big")  # where an Ethernet frame says its type (bytes 12-13)


def check_version(installed: str) -> str | None:
    """Why the installed pysoem cannot be trusted with Prime's frames beside it (None: it is the tested one)."""
    if installed == TESTED_PYSOEM:
        return None
    return (f"pysoem {installed} is installed, but Prime's EtherCAT layer was verified against pysoem {TESTED_PYSOEM} "
            f"(the frame indices and mailbox use of the SOEM it bundles); install it with "
            f"`pip install pysoem=={TESTED_PYSOEM}`")


def check_indices(indices: Iterable[int]) -> str | None:
    """Why SOEM's frames seen during its ring scan break the split of frame indices (None: they keep to it)."""
    outside = sorted({index for index in indices if not 0 <= index < EC_MAXBUF})
    if not outside:
        return None
    shown = ", ".join(f"0x{index:02X}" for index in outside[:4])
    clash = " inside the range Prime keeps for its own frames" if outside[-1] >= FIRST_INDEX else ""
    return (f"SOEM sent frames with index {shown}{clash}, not 0..{EC_MAXBUF - 1} as the pysoem {TESTED_PYSOEM} it was "
            "verified against does; Prime's frames and SOEM's could be taken for each other")


class FrameWatch(Protocol):
    """Sees the frames on a NIC from when it is opened; ``indices()`` gives those seen since the last call."""

    def indices(self) -> list[int]: ...

    def close(self) -> None: ...


class SocketWatch:
    """A packet socket on ``interface`` that only looks: every EtherCAT frame sent from this host, by its index. It
    takes every protocol (ETH_P_ALL), since the kernel shows a packet socket the frames its host sends only then. It
    is opened for no protocol and given ETH_P_ALL in ``bind``: a socket opened for a protocol takes that protocol from
    every NIC until it is bound, and frames of other masters on other NICs (Prime's own, in their indices) queued in
    it meanwhile."""

    def __init__(self, interface: str) -> None:
        self.interface = interface
        self._sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, WATCH_BUFFER)
            self._sock.bind((interface, ETH_P_ALL))
            self.interface = self._sock.getsockname()[0]  # the kernel's name for it (frames carry that one)
            self._sock.setblocking(False)
        except BaseException:
            self._sock.close()
            raise

    def indices(self) -> list[int]:
        """The indices of the frames sent from this host since the last call. A reply is left out: one that comes
        back late to a frame of an earlier master on the NIC (a command that has ended) says nothing of SOEM's."""
        seen: list[int] = []
        while True:
            try:
                frame, address = self._sock.recvfrom(2048)
            except BlockingIOError:
                return seen
            if address[0] != self.interface or address[2] != socket.PACKET_OUTGOING or frame[12:14] != ETHERTYPE_BYTES:
                continue
            index = frame_index(frame)
            if index is not None:
                seen.append(index)

    def close(self) -> None:
        self._sock.close()


class QueueKeeper:
    """Counts the replies of Prime's that may wait in SOEM's socket and, at ``limit`` of them, has SOEM read its
    socket by calling ``drain`` (a frame of SOEM's own, which it reads its socket up to, dropping ours on the way).
    The cycle reads it too: ``sending()`` as SOEM sends a cycle frame, ``read()`` once it has received it (the
    replies of Prime's that came before that frame's are gone then)."""

    def __init__(self, drain: Callable[[], object], limit: int = QUEUE_LIMIT) -> None:
        self.drain = drain
        self.limit = limit
        self.drains = 0
        self._since = 0
        self._before_cycle = 0
        self._lock = threading.Lock()

    def sent(self) -> None:
        """One frame of Prime's went out (its reply will queue in SOEM's socket)."""
        with self._lock:
            self._since += 1
            if self._since < self.limit:
                return
            self._since = self._before_cycle = 0
            self.drains += 1
        self.drain()

    def sending(self) -> None:
        with self._lock:
            self._before_cycle = self._since

    def read(self) -> None:
        with self._lock:
            self._since = max(self._since - self._before_cycle, 0)
            self._before_cycle = 0
