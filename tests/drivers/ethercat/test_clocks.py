"""Distributed clocks over our own frames, against the emulated ESC's clock: SYNC0 armed on a cycle boundary, and a
returning slave's clock put back on the ring's time, whichever way its ESC reads the sign of the difference."""

from __future__ import annotations

import struct

import pytest

from doubles.link import EmulatedClock, RingHub
from doubles.wire import STATION_BASE, WireMaster
from humanoid_prime.drivers.ethercat.clocks import RingClocks
from humanoid_prime.drivers.ethercat.registers import RingRegisters
from humanoid_prime.virtual.ring.options import RingOptions
from humanoid_prime.virtual.ring.ring import Ring

SLAVES = 4
CYCLE_NS = 10_000_000


def make() -> tuple[Ring, RingHub, RingClocks]:
    clock = EmulatedClock()
    ring = Ring(RingOptions(slaves=SLAVES), clock=lambda: round(clock.now * 1e9))
    setup = WireMaster(ring, round(clock.now * 1e9))
    setup.bring_to_safeop()
    hub = RingHub(ring, clock)

    def cycles(count: int) -> bool:  # the cycle's time distribution, every millisecond
        for _ in range(count):
            clock.sleep(0.001)
            setup.now_ns = round(clock.now * 1e9) - 1_000_000
            setup.cycle([b"\0" * 14] * SLAVES, 1_000_000)
        return True

    registers = RingRegisters(hub.port, SLAVES, clock=clock)
    return ring, hub, RingClocks(registers, [True] * SLAVES, [700 * k for k in range(SLAVES)], cycles)


def offsets_written(hub: RingHub, k: int) -> list[int]:
    out = []
    for frame in hub.sent:
        command, _i, adp, ado = struct.unpack_from("<BBHH", frame, 16)
        if command == 0x05 and adp == STATION_BASE + k and ado == 0x0920:
            out.append(struct.unpack_from("<Q", frame, 26)[0])
    return out


def now_ns(ring: Ring) -> int:
    return ring.clock()


def restart_clock(esc, now: int) -> None:
    """What a power cycle does to an ESC's clock: local time from 0, offset and delay cleared."""
    esc.clock.origin_ns = now
    esc.write(0x0920, bytes(12), 0, 12)


@pytest.mark.parametrize("reversed_sign", [False, True])
def test_a_clock_250_us_behind_is_corrected_by_the_difference_its_esc_measures_either_way_it_reads_the_sign(
        reversed_sign):
    ring, hub, clocks = make()
    esc = ring.slaves[2].esc
    esc.clock.difference_reversed = reversed_sign
    offset = struct.unpack_from("<Q", esc.mem, 0x0920)[0]
    esc.write(0x0920, struct.pack("<Q", (offset - 250_000) % (1 << 64)), 0, 8)
    assert clocks.set_clock(2, lambda j: True) is None
    written = [(value - offset + (1 << 63)) % (1 << 64) - (1 << 63) for value in offsets_written(hub, 2)]
    # the ESC that reads bit 31 the other way: the first correction doubles the difference, so it is turned round
    assert written == pytest.approx([1_400] if not reversed_sign else [-501_400, 1_400], abs=1)
    assert esc.clock.system_time(now_ns(ring)) == ring.slaves[0].esc.clock.system_time(now_ns(ring))


def test_a_clock_back_from_a_power_cycle_is_stepped_onto_the_reference_s_time_with_the_delay_measured_before():
    ring, hub, clocks = make()
    esc = ring.slaves[3].esc
    restart_clock(esc, now_ns(ring))
    assert clocks.set_clock(3, lambda j: True) is None
    (first, *_rest) = [frame for frame in hub.sent if frame[16] == 0x05 and frame[20:22] == b"\x20\x09"]
    assert struct.unpack_from("<H", first, 22)[0] & 0x7FF == 12  # offset and delay in one write, as IgH does
    assert struct.unpack_from("<I", first, 34)[0] == 2_100  # the delay config_dc measured for ring 3
    assert esc.clock.system_time(now_ns(ring)) == ring.slaves[0].esc.clock.system_time(now_ns(ring))


def test_the_reference_clock_is_set_to_the_time_of_a_slave_that_kept_its_clock():
    ring, _hub, clocks = make()
    restart_clock(ring.slaves[0].esc, now_ns(ring))
    assert clocks.set_clock(0, lambda j: j != 0) is None
    assert ring.slaves[0].esc.clock.system_time(now_ns(ring)) == ring.slaves[1].esc.clock.system_time(now_ns(ring))


def test_a_clock_that_will_not_come_into_step_says_so():
    ring, _hub, clocks = make()
    ring.slaves[1].esc.clock.difference_error_ns = 50_000
    assert clocks.set_clock(1, lambda j: True) == (
        "its clock did not come into step with the ring's: 50000 ns off after 4 corrections (SYNC0 needs it within "
        "10000 ns)")


def test_sync0_is_armed_on_a_cycle_boundary_at_least_100_ms_ahead_of_the_slave_s_time():
    ring, _hub, clocks = make()
    esc = ring.slaves[1].esc
    clocks.arm_sync0(1, CYCLE_NS)
    start = esc.clock.sync0_start_ns
    assert esc.clock.activation == 0x03 and esc.clock.sync0_cycle_ns == CYCLE_NS
    assert start % CYCLE_NS == 0 and 100_000_000 <= start - esc.clock.system_time(now_ns(ring)) <= 110_000_000
