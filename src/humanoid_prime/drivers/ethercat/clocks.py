"""Distributed clocks over Prime's own frames: SYNC0 armed on a slave, and a returning slave's clock put back in
step with the ring's before its SYNC0 starts again.

SOEM's ``config_dc`` measures the ring and sets every slave's offset at bring-up; nothing in SOEM sets them again
for a slave back from a power cycle, whose local clock starts from 0 with its offset (0x0920) and delay (0x0928)
cleared: SYNC0 would run on a clock years off the ring's, out of step with the frames. ``RingClocks.set_clock``
does what IgH's master does for a slave it finds reset.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence

from humanoid_prime.drivers.ethercat.registers import NoReply, RingRegisters
from humanoid_prime.drivers.ethercat.wire import (
    DC_CYCLIC_SYNC0,
    DC_DIFFERENCE_MASK,
    DC_LOCAL_SMALLER,
    REG_DC_ACTIVATION,
    REG_DC_CYCLE_UNIT,
    REG_DC_DIFFERENCE,
    REG_DC_OFFSET,
    REG_DC_SPEED_START,
    REG_DC_SYNC0_CYCLE,
    REG_DC_SYNC0_START,
    REG_DC_SYSTEM_TIME,
)

CLOCK_STEP_NS = 1_000_000  # a clock further off than this gets a new offset at once (IgH's EC_SYSTEM_TIME_TOLERANCE_NS)
CLOCK_SYNC_WINDOW_NS = 10_000  # in step with the ring (IgH waits for it before starting SYNC0: EC_DC_MAX_SYNC_DIFF_NS)
CLOCK_FILTER_FRAMES = 16  # time distributions to let through after a filter reset before the difference is read
CLOCK_CORRECTIONS = 4  # offset corrections by the measured difference before a clock counts as not coming into step
SYNC0_START_DELAY_NS = 100_000_000  # the first SYNC0 this long after now, on a cycle boundary (SOEM's SyncDelay)
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CLOCK = struct.Struct("<QQQ")  # 0x0910 system time, 0x0918 receive time, 0x0920 offset: read in one datagram
_OFFSET_DELAY = struct.Struct("<QI")  # 0x0920 offset and 0x0928 delay: written in one datagram, as IgH does


class RingClocks:
    """The clocks of the slaves whose ESC has one (``has_dc[k]``, with the delay ``delays[k]`` that config_dc
    measured). ``cycles(count)`` waits until the cycle has brought the reference clock's time ``count`` times
    (False if it did not in time, or the master closes)."""

    def __init__(self, registers: RingRegisters, has_dc: Sequence[bool], delays: Sequence[int],
                 cycles: Callable[[int], bool]) -> None:
        self.registers = registers
        self.has_dc = list(has_dc)
        self.delays = list(delays)
        self.cycles = cycles
        self.reference = next((k for k, dc in enumerate(self.has_dc) if dc), None)  # SOEM's: the first with DC

    def arm_sync0(self, k: int, cycle_ns: int) -> None:
        """SYNC0 on slave ``k`` every ``cycle_ns``, from the next cycle boundary 0.1 s on (SOEM's ``ecx_dcsync0``,
        one register at a time over our frames; the start time from the slave's own system time)."""
        registers = self.registers
        registers.write(k, REG_DC_ACTIVATION, b"\x00")
        registers.write(k, REG_DC_CYCLE_UNIT, b"\x00")
        now = _U64.unpack(registers.read(k, REG_DC_SYSTEM_TIME, 8))[0]
        start = ((now + SYNC0_START_DELAY_NS) // cycle_ns) * cycle_ns + cycle_ns
        registers.write(k, REG_DC_SYNC0_START, _U64.pack(start & 0xFFFFFFFFFFFFFFFF))
        registers.write(k, REG_DC_SYNC0_CYCLE, _U32.pack(cycle_ns))
        registers.write(k, REG_DC_ACTIVATION, bytes((DC_CYCLIC_SYNC0,)))

    def set_clock(self, k: int, in_step: Callable[[int], bool]) -> str | None:
        """Bring ring ``k``'s system time back onto the ring's; None once it is within ``CLOCK_SYNC_WINDOW_NS``, else
        why not. ``in_step(j)``: slave ``j`` kept its clock (it is in SAFE-OP or OP and was not reconfigured).

        A clock more than ``CLOCK_STEP_NS`` off gets a new offset at once, written with the delay measured at
        bring-up; the time it is compared with is another clock's, read in the next frame (the reference clock's,
        or for the reference clock itself that of the first slave that kept its own). Then the difference the ESC
        measures against the time distribution (0x092C) is read, after a filter reset and ``CLOCK_FILTER_FRAMES``
        cycles, and taken off the offset until it is within ``CLOCK_SYNC_WINDOW_NS``, at most ``CLOCK_CORRECTIONS``
        times."""
        reference = self.reference
        if not self.has_dc[k] or reference is None:
            return None
        if k == reference:  # compared with, and measured by, a slave that kept its clock: not one reconfigured
            kept = next((j for j in range(len(self.has_dc)) if j != k and self.has_dc[j] and in_step(j)), None)
            if kept is None:
                return None  # every clock started again: the others are set to this one's
            other, measured, sign = kept, kept, -1
        else:
            other, measured, sign = reference, k, 1
        registers = self.registers
        try:
            own, _received, offset = _CLOCK.unpack(registers.read(k, REG_DC_SYSTEM_TIME, _CLOCK.size))
            step = _signed64(_U64.unpack(registers.read(other, REG_DC_SYSTEM_TIME, 8))[0] - own)
            if abs(step) > CLOCK_STEP_NS:
                offset = (offset + step) & 0xFFFFFFFFFFFFFFFF
                registers.write(k, REG_DC_OFFSET, _OFFSET_DELAY.pack(offset, self.delays[k]))
            before = None
            for _ in range(CLOCK_CORRECTIONS + 1):
                difference = self._difference(measured)
                if difference is None:
                    return "its clock could not be compared with the ring's: no time distribution reached it"
                difference *= sign
                if abs(difference) <= CLOCK_SYNC_WINDOW_NS:
                    return None
                if before is not None and abs(difference) > abs(before):
                    # the correction made it worse: this ESC reads bit 31 the other way round (ESC documents
                    # disagree on it), so the last correction goes back and this one the other way
                    sign, difference = -sign, -difference
                before = difference
                offset = (offset + difference) & 0xFFFFFFFFFFFFFFFF
                registers.write(k, REG_DC_OFFSET, _U64.pack(offset))
        except NoReply:
            return "its clock registers did not answer"
        return (f"its clock did not come into step with the ring's: {difference} ns off after {CLOCK_CORRECTIONS} "
                f"corrections (SYNC0 needs it within {CLOCK_SYNC_WINDOW_NS} ns)")

    def _difference(self, k: int) -> int | None:
        """Ring ``k``'s 0x092C as signed ns (the reference clock's time minus its own) over the time distributions
        of ``CLOCK_FILTER_FRAMES`` cycles after a filter reset; None when the cycle brought none in time."""
        registers = self.registers
        registers.write(k, REG_DC_SPEED_START, registers.read(k, REG_DC_SPEED_START, 2))
        if not self.cycles(CLOCK_FILTER_FRAMES):
            return None
        raw: int = _U32.unpack(registers.read(k, REG_DC_DIFFERENCE, 4))[0]
        magnitude = raw & DC_DIFFERENCE_MASK
        return magnitude if raw & DC_LOCAL_SMALLER else -magnitude


def _signed64(value: int) -> int:
    value &= 0xFFFFFFFFFFFFFFFF
    return value - (1 << 64) if value >= 1 << 63 else value
