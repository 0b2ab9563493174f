"""The distributed clock of one emulated ESC, as the master sees it in registers 0x0900-0x09A7.

- 0x0900-0x090F receive times of ports 0-3 (latched by any write to 0x0900), 0x0910 system time (u64, local time +
  0x0920 offset; a write is a drift sample from the reference clock and does not set the time), 0x0918 local time
  of the latching frame (u64), 0x0920 system time offset (u64), 0x0928 propagation delay, 0x092C system time
  difference (received minus local in bits 0-30, saturated; bit 31 set when the local copy is the smaller, as
  Infineon's XMC4300 register description spells it), 0x0930 speed counter start (0x1000 after power-on; a write
  resets the difference filter, as the clock initialisation of Beckhoff's ESC datasheet, section I 9.1.3.6, uses
  it), 0x0980 cycle unit control, 0x0981 activation (bit 0 cyclic operation, bit 1 SYNC0, bit 2 SYNC1), 0x0990
  SYNC0 start time (u64 system time), 0x09A0 SYNC0 cycle time (u32 ns), 0x09A4 SYNC1 cycle time.
- The local clock starts at 0 at power-on and the offset is cleared, so a slave back from a power cycle is far off
  the ring's time until the master sets its offset again. There is no time control loop: the difference stays as
  the master left it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from humanoid_prime.drivers.ethercat.wire import (
    DC_CYCLIC_SYNC0,
    DC_DIFFERENCE_MASK,
    DC_LOCAL_SMALLER,
    REG_DC_ACTIVATION,
    REG_DC_DIFFERENCE,
    REG_DC_FRAME_TIME,
    REG_DC_OFFSET,
    REG_DC_RECEIVE_TIME,
    REG_DC_SPEED_START,
    REG_DC_SYNC0_CYCLE,
    REG_DC_SYNC0_START,
    REG_DC_SYSTEM_TIME,
)

_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_I64 = struct.Struct("<q")
SPEED_START_POWER_ON = 0x1000


def _overlaps(span: tuple[int, int], start: int, length: int) -> bool:
    return span[0] < start + length and span[1] > start


class EscClock:
    """The clock registers of one ESC in its register memory ``mem``; ``frame_time()`` is the time (monotonic ns) of
    the frame being processed, ``activation_changed()`` tells the firmware that 0x0981 was written."""

    def __init__(self, mem: bytearray, frame_time: Callable[[], int], activation_changed: Callable[[], None], *,
                 origin_ns: int) -> None:
        self.mem = mem
        self.frame_time = frame_time
        self.activation_changed = activation_changed
        self.origin_ns = origin_ns
        self.port0_delay_ns = 0
        self.port1_delay_ns: int | None = None
        self.samples = 0
        self.difference_ns: int | None = None  # received minus local system time at the last sample
        self.sample_ns: int | None = None  # frame time of that sample
        self.sync0_missed = False
        self.offset_ns = 0
        self.activation = 0
        self.sync0_start_ns = 0
        self.sync0_cycle_ns = 0
        # quirks of some ESCs: bit 31 of 0x092C read the other way round (ESC documents disagree on it), and a
        # clock whose difference stays this far off whatever offset it is given (it never comes into step)
        self.difference_reversed = False
        self.difference_error_ns = 0

    def power_on(self, now_ns: int | None) -> None:
        """Registers as after power-up (the memory already cleared); the local clock starts again at ``now_ns``."""
        if now_ns is not None:
            self.origin_ns = now_ns
        self.difference_ns = self.sample_ns = None
        self.sync0_missed = False
        struct.pack_into("<H", self.mem, REG_DC_SPEED_START, SPEED_START_POWER_ON)
        self._update()

    def local_time(self, now_ns: int) -> int:
        return now_ns - self.origin_ns

    def system_time(self, now_ns: int) -> int:
        return (now_ns - self.origin_ns + self.offset_ns) & 0xFFFFFFFFFFFFFFFF

    def sync0_running(self, now_ns: int) -> bool:
        """SYNC0 pulses are being generated: cyclic operation and SYNC0 on, start time reached."""
        return (self.activation & DC_CYCLIC_SYNC0 == DC_CYCLIC_SYNC0 and not self.sync0_missed
                and self.system_time(now_ns) >= self.sync0_start_ns)

    # ---- register access -----------------------------------------------------------------------------------------
    def before_read(self, address: int, end: int) -> None:
        """A read of ``address``..``end``: the system time register shows the time of this frame."""
        if address < REG_DC_SYSTEM_TIME + 8 and end > REG_DC_SYSTEM_TIME:
            _U64.pack_into(self.mem, REG_DC_SYSTEM_TIME, self.system_time(self.frame_time()))

    def time_distribution(self, address: int, data: bytes | bytearray) -> bool:
        """A write that lies within the system time register: the reference clock's time, every cycle (True; the
        register keeps the local copy)."""
        end = address + len(data)
        if address >= REG_DC_SYSTEM_TIME and end <= REG_DC_SYSTEM_TIME + 8:
            if end - address >= 4:
                self._drift_sample(bytes(data))
            return True
        return False

    def written(self, address: int, data: bytes | bytearray) -> None:
        """The master wrote ``data`` at ``address`` (the memory already holds it, except the system time)."""
        end = address + len(data)
        touched = (address, end)
        drift = None
        if address < REG_DC_SYSTEM_TIME + 8 and end > REG_DC_SYSTEM_TIME:
            lo, hi = max(address, REG_DC_SYSTEM_TIME), min(end, REG_DC_SYSTEM_TIME + 8)
            drift = bytes(data[lo - address:hi - address])
        if _overlaps(touched, REG_DC_OFFSET, 8) or _overlaps(touched, REG_DC_ACTIVATION, 0x27):
            self._update()
        if _overlaps(touched, REG_DC_RECEIVE_TIME, 4):
            self._latch_receive_times()
        if _overlaps(touched, REG_DC_SPEED_START, 2):
            self._reset_filter()
        if drift is not None and len(drift) >= 4:
            self._drift_sample(drift)
        if _overlaps(touched, REG_DC_ACTIVATION, 1):
            self._activation_written()

    # ---- inside ----------------------------------------------------------------------------------------------------
    def _update(self) -> None:
        mem = self.mem
        self.offset_ns = _I64.unpack_from(mem, REG_DC_OFFSET)[0]
        self.activation = mem[REG_DC_ACTIVATION]
        self.sync0_start_ns = _U64.unpack_from(mem, REG_DC_SYNC0_START)[0]
        self.sync0_cycle_ns = _U32.unpack_from(mem, REG_DC_SYNC0_CYCLE)[0]

    def _latch_receive_times(self) -> None:
        local = self.local_time(self.frame_time())
        port0 = local + self.port0_delay_ns
        port1 = 0 if self.port1_delay_ns is None else local + self.port1_delay_ns
        struct.pack_into("<IIII", self.mem, REG_DC_RECEIVE_TIME, port0 & 0xFFFFFFFF, port1 & 0xFFFFFFFF, 0, 0)
        _U64.pack_into(self.mem, REG_DC_FRAME_TIME, port0 & 0xFFFFFFFFFFFFFFFF)

    def _drift_sample(self, written: bytes) -> None:
        now = self.frame_time()
        own = self.system_time(now)
        width = len(written)
        received = int.from_bytes(written, "little")
        mask = (1 << (8 * width)) - 1
        diff = (received - (own & mask)) & mask
        if diff >= 1 << (8 * width - 1):
            diff -= 1 << (8 * width)
        diff = self.difference_error_ns or diff
        magnitude = min(abs(diff), DC_DIFFERENCE_MASK)
        smaller = (diff > 0) != self.difference_reversed
        _U32.pack_into(self.mem, REG_DC_DIFFERENCE, magnitude | (DC_LOCAL_SMALLER if smaller else 0))
        self.difference_ns = diff
        self.sample_ns = now
        self.samples += 1

    def _reset_filter(self) -> None:
        _U32.pack_into(self.mem, REG_DC_DIFFERENCE, 0)
        self.difference_ns = self.sample_ns = None

    def _activation_written(self) -> None:
        if self.activation & DC_CYCLIC_SYNC0 == DC_CYCLIC_SYNC0:
            self.sync0_missed = self.sync0_start_ns < self.system_time(self.frame_time())
        else:
            self.sync0_missed = False
        self.activation_changed()
