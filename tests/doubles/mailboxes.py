"""A test double of ten eRob mailboxes: gain registers that ignore writes while the gate is 0, each object
held in its own size (the gains u16 as in the vendor EDS, or u32 as one host reads them) and a write of
another length aborted as a CoE stack that enforces sizes does."""

from __future__ import annotations

import threading
import time

from humanoid_prime.drivers.erob.objects import (
    BUS_GAIN_GATE,
    FOLLOWING_ERROR_WINDOW,
    POS_LOOP_GAIN,
    VEL_LOOP_GAIN,
    VEL_LOOP_INTEGRAL,
)
from humanoid_prime.errors import PrimeError

NAMES = {POS_LOOP_GAIN: "pos_reg", VEL_LOOP_GAIN: "vel_reg", VEL_LOOP_INTEGRAL: "integral", BUS_GAIN_GATE: "gate",
         (FOLLOWING_ERROR_WINDOW, 0): "window"}
FACTORY_WINDOW = 41722  # counts, about 0.5 rad


class DriveMailboxes:
    def __init__(self, positions=range(10), *, latency_s: float = 0.0, initial=(300, 94, 5),
                 gain_bytes: int = 2) -> None:
        self.latency_s = latency_s
        self.values = {p: {"gate": 0, "pos_reg": initial[0], "vel_reg": initial[1], "integral": initial[2],
                           "window": FACTORY_WINDOW} for p in positions}
        self.sizes = {"gate": 4, "pos_reg": gain_bytes, "vel_reg": gain_bytes, "integral": gain_bytes, "window": 4}
        self.log: list[tuple[float, int, str, int]] = []  # accepted writes
        self.fail_next: dict[int, int] = {}  # position -> number of writes to refuse
        self.dead: set[int] = set()
        self.held: dict[int, threading.Event] = {}  # position -> writes there wait until the event is set
        self.reads_held: threading.Event | None = None  # reads wait until it is set
        self.meet: threading.Event | None = None  # transfers wait here until two have been in flight at once
        self.slow: dict[int, float] = {}  # position -> its mailbox service time, instead of latency_s
        self.in_flight = 0  # transfers being served now, and the most ever served at once
        self.most_in_flight = 0
        self._lock = threading.Lock()

    def _check(self, position: int, index: int, sub: int) -> str:
        if position in self.dead:
            raise PrimeError(f"ring {position}: no answer (working counter 0)")
        if position not in self.values:
            raise PrimeError(f"ring {position}: no such slave")
        try:
            return NAMES[(index, sub)]
        except KeyError:
            raise PrimeError(f"ring {position}: SDO abort 0x06020000 on 0x{index:04X}:{sub:02X}") from None

    def _serve(self, position: int) -> None:
        """The mailbox service time, counting how many transfers overlap."""
        with self._lock:
            self.in_flight += 1
            self.most_in_flight = max(self.most_in_flight, self.in_flight)
            if self.meet is not None and self.in_flight >= 2:
                self.meet.set()
        try:
            if self.meet is not None:
                self.meet.wait(30.0)
            time.sleep(self.slow.get(position, self.latency_s))
        finally:
            with self._lock:
                self.in_flight -= 1

    def sdo_read(self, position: int, index: int, sub_index: int) -> bytes:
        name = self._check(position, index, sub_index)
        if self.reads_held is not None:
            self.reads_held.wait()
        self._serve(position)
        return self.values[position][name].to_bytes(self.sizes[name], "little")

    def hold(self, position: int) -> threading.Event:
        """Writes to ``position`` wait until the returned event is set."""
        release = self.held[position] = threading.Event()
        return release

    def sdo_write(self, position: int, index: int, sub_index: int, data: bytes) -> None:
        name = self._check(position, index, sub_index)
        if position in self.held:
            self.held[position].wait()
        self._serve(position)
        with self._lock:
            if self.fail_next.get(position, 0) > 0:
                self.fail_next[position] -= 1
                raise PrimeError(f"ring {position}: SDO timeout")
            if len(data) != self.sizes[name]:
                raise PrimeError(f"ring {position}: SDO abort 0x06070010 on 0x{index:04X}:{sub_index:02X} (data "
                                 f"type does not match: {len(data)} bytes for a {self.sizes[name]}-byte object)")
            value = int.from_bytes(data, "little")
            regs = self.values[position]
            if name in ("pos_reg", "vel_reg", "integral") and regs["gate"] != 1:
                return  # the drive silently ignores gain writes unless the gate is armed
            regs[name] = value
            self.log.append((time.monotonic(), position, name, value))

    def registers(self, position: int) -> tuple[int, int, int]:
        r = self.values[position]
        return r["pos_reg"], r["vel_reg"], r["integral"]
