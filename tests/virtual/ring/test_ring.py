"""The slave ring seen through frames, without a network: addressing, working counters, EEPROM, AL
states, mailbox, process data, the DC lock model and its faults."""

from __future__ import annotations

import struct

import pytest

from doubles.wire import STATION_BASE, WireMaster
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD
from humanoid_prime.drivers.erob.objects import POWER_UP_RXPDO, POWER_UP_TXPDO, RXPDO_STRUCT, TXPDO_STRUCT
from humanoid_prime.drivers.ethercat.wire import Command
from humanoid_prime.virtual.ring.frames import Datagram, build_frame, parse_frame
from humanoid_prime.virtual.ring.mailbox import sdo_abort_code
from humanoid_prime.virtual.ring.options import RingOptions
from humanoid_prime.virtual.ring.ring import Ring

START_NS = 5_000_000_000_000
MS = 1_000_000
IDLE_OUTPUT = RXPDO_STRUCT.pack(0, 0, 0, 0, 8)


def make(slaves: int = 3, **options: object) -> tuple[Ring, WireMaster]:
    ring = Ring(RingOptions(slaves=slaves, **options), clock=lambda: START_NS)
    return ring, WireMaster(ring, START_NS)


def in_safeop(slaves: int = 3, sync0_ns: int | None = 10 * MS, **options: object) -> tuple[Ring, WireMaster]:
    ring, master = make(slaves, **options)
    master.bring_to_safeop()
    if sync0_ns is not None:
        for i in range(slaves):
            master.start_sync0(STATION_BASE + i, sync0_ns)
    return ring, master


def request_op(master: WireMaster, slaves: int) -> None:
    for i in range(slaves):
        master.request_state(STATION_BASE + i, 0x08)


def states(master: WireMaster, slaves: int) -> list[tuple[int, int]]:
    return [master.al_status(STATION_BASE + i) for i in range(slaves)]


def run_cycles(master: WireMaster, count: int, period_ns: int, outputs: list[bytes] | None = None,
               distribute_time: bool = True) -> tuple[int, list[bytes]]:
    outputs = outputs or [IDLE_OUTPUT] * len(master.ring.reachable)
    result = (0, [])
    for _ in range(count):
        result = master.cycle(outputs, period_ns, distribute_time)
    return result


def in_op(slaves: int = 3, **options: object) -> tuple[Ring, WireMaster]:
    ring, master = in_safeop(slaves, dc_lock_cycles=5, **options)
    request_op(master, slaves)
    run_cycles(master, 10, MS)
    assert all(status == 0x08 for status, _code in states(master, slaves))
    return ring, master


def enable_outputs(slaves: int, controlword: int, target: int = 0) -> list[bytes]:
    return [RXPDO_STRUCT.pack(controlword, target, 0, 0, 8)] * slaves


# ---- addressing and working counters ---------------------------------------------------------------------
def test_broadcast_read_counts_every_slave():
    _ring, master = make(10)
    assert master.brd(0x0000, 2).wkc == 10


def test_broadcast_read_returns_the_or_of_the_slaves_data():
    ring, master = make(3)
    master.set_station_addresses()
    assert master.brd(0x0010, 2).data == struct.pack("<H", 0x1001 | 0x1002 | 0x1003)


def test_auto_increment_write_sets_station_addresses_in_ring_order():
    ring, master = make(3)
    master.set_station_addresses()
    assert [s.esc.station_address for s in ring.slaves] == [0x1001, 0x1002, 0x1003]


def test_each_slave_adds_one_to_the_auto_increment_address():
    _ring, master = make(4)
    assert master.aprd(2, 0x0000, 1).adp == (-2 + 4) & 0xFFFF


def test_configured_address_read_of_no_slave_has_working_counter_zero():
    _ring, master = make(2)
    master.set_station_addresses()
    assert master.fprd(0x2000, 0x0130, 2).wkc == 0
    assert master.fprd(0x1002, 0x0130, 2).wkc == 1


def test_esc_reports_dc_support_and_both_ports():
    _ring, master = make(2)
    master.set_station_addresses()
    assert struct.unpack("<H", master.fprd(0x1001, 0x0008, 2).data)[0] & 0x0004
    assert struct.unpack("<H", master.fprd(0x1001, 0x0110, 2).data)[0] & 0x0F00 == 0x0A00  # ports 0, 1 open
    assert struct.unpack("<H", master.fprd(0x1002, 0x0110, 2).data)[0] & 0x0F00 == 0x0600  # port 1 closed


def test_status_registers_are_read_only_for_the_master():
    _ring, master = make(1)
    master.set_station_addresses()
    master.fpwr(0x1001, 0x0130, b"\x08\x00")
    assert master.al_status(0x1001) == (0x01, 0)


def test_eeprom_read_delivers_eight_bytes_of_the_sii():
    _ring, master = make(1)
    master.set_station_addresses()
    master.fpwr(0x1001, 0x0502, struct.pack("<HI", 0x0100, 0x0008))
    status = struct.unpack("<H", master.fprd(0x1001, 0x0502, 2).data)[0]
    assert status & 0x8000 == 0 and status & 0x0040
    assert struct.unpack("<II", master.fprd(0x1001, 0x0508, 8).data) == (0x5A65726F, 0x00029252)


def test_malformed_frame_is_dropped():
    ring, _master = make(1)
    assert not ring.process(bytearray(b"\xff" * 12 + b"\x88\xa4" + b"\xff\x1f"), START_NS)
    assert ring.dropped_malformed == 1


# ---- AL state machine -----------------------------------------------------------------------------------------
def test_init_to_safeop_is_refused_with_0x0011():
    _ring, master = make(1)
    master.set_station_addresses()
    master.request_state(0x1001, 0x04)
    assert master.al_status(0x1001) == (0x11, 0x0011)


def test_preop_needs_the_mailbox_sync_managers():
    _ring, master = make(1)
    master.set_station_addresses()
    master.request_state(0x1001, 0x02)
    assert master.al_status(0x1001) == (0x11, 0x0016)


def test_error_needs_acknowledging_before_going_up():
    _ring, master = make(1)
    master.set_station_addresses()
    master.request_state(0x1001, 0x04)
    master.program_mailbox(0x1001)
    master.request_state(0x1001, 0x02)
    assert master.al_status(0x1001) == (0x11, 0x0011)
    master.request_state(0x1001, 0x12)
    assert master.al_status(0x1001) == (0x02, 0)


def test_frames_that_arrive_during_a_step_are_answered_between_its_parts():
    # an ESC answers in microseconds; one step of the emulated robot's Python takes hundreds of them, and a
    # master's state read (which pysoem makes holding its interpreter lock) would wait the whole step out
    ring, master = in_op(2)
    answered: list[Datagram] = []

    def serve() -> None:  # each time the step looks, a frame has come in 0.6 ms later than the last
        master.now_ns += 600_000
        frame = bytearray(build_frame([Datagram(Command.FPRD, bytes(2), adp=STATION_BASE, ado=0x0130)]))
        assert ring.process(frame, master.now_ns)
        answered.append(parse_frame(frame)[0])

    checked: list[int] = []
    tick = ring.slaves[0].tick
    ring.slaves[0].tick = lambda now_ns: (checked.append(now_ns), tick(now_ns))
    ring.serve_waiting = serve
    ring.advance(master.now_ns + MS)  # one physics step
    # before the plant, after it, and before the timed checks
    assert [(d.wkc, d.data) for d in answered] == [(1, struct.pack("<H", 0x08))] * 3
    assert ring._pending_frame is None  # the slaves' reaction to it ran there too, not at the next step
    assert checked == [master.now_ns]  # the timed checks never run at a time before a frame already answered


def test_an_output_watchdog_does_not_run_out_on_a_frame_that_waited_while_the_emulator_was_not_running():
    # a host that did not run the emulator for 150 ms: the master's frames queued meanwhile reached the ESCs,
    # which are hardware on the robot; the watchdog (100 ms) counts them before it looks
    ring, master = in_op(1)
    queued = [True]

    def serve() -> None:  # the frame that waited in the socket, with the outputs the master kept sending
        if queued and queued.pop():
            image = IDLE_OUTPUT + bytes(TXPDO_STRUCT.size)
            master.exchange([Datagram.logical(Command.LRW, 0, image),
                             Datagram(Command.FRMW, bytes(8), adp=STATION_BASE, ado=0x0910)])

    ring.serve_waiting = serve
    master.now_ns += 150 * MS
    ring.advance(master.now_ns, max_steps=0)
    assert states(master, 1) == [(0x08, 0)]


def test_a_slow_firmware_shows_the_old_state_until_its_state_change_is_done():
    ring, master = make(1, state_change_s=0.05)
    master.set_station_addresses()
    master.program_mailbox(0x1001)
    master.request_state(0x1001, 0x02)
    assert master.al_status(0x1001) == (0x01, 0)
    master.now_ns += 30 * MS
    ring.advance(master.now_ns)
    master.request_state(0x1001, 0x02)  # asked again while under way: it goes on, it does not start over
    assert master.al_status(0x1001) == (0x01, 0)
    master.now_ns += 30 * MS
    ring.advance(master.now_ns)
    assert master.al_status(0x1001) == (0x02, 0)


def test_safeop_needs_sm2_matching_the_rxpdo_size():
    _ring, master = make(1)
    master.set_station_addresses()
    master.program_mailbox(0x1001)
    master.request_state(0x1001, 0x12)
    master.program_process_data(0)
    master.fpwr(0x1001, 0x0810, struct.pack("<HHI", 0x1100, RXPDO_STRUCT.size + 1, 0x00010064))
    master.request_state(0x1001, 0x04)
    assert master.al_status(0x1001) == (0x12, 0x001D)


def test_safeop_counts_only_inputs_in_the_working_counter():
    _ring, master = in_safeop(3)
    wkc, inputs = run_cycles(master, 1, MS)
    assert wkc == 3
    assert struct.unpack_from("<H", inputs[0])[0] == 0x0250


def test_op_counts_outputs_twice_and_inputs_once():
    _ring, master = in_op(3)
    wkc, _inputs = run_cycles(master, 1, MS)
    assert wkc == 3 * 3


# ---- DC lock model ---------------------------------------------------------------------------------------------
def test_op_request_waits_for_the_dc_lock_cycles():
    _ring, master = in_safeop(2, dc_lock_cycles=50)
    request_op(master, 2)
    run_cycles(master, 2 + 40, MS)  # the first 2 ms pass before SYNC0 starts
    assert states(master, 2) == [(0x04, 0), (0x04, 0)]
    run_cycles(master, 10, MS)
    assert states(master, 2) == [(0x08, 0), (0x08, 0)]


def test_lock_needs_the_time_distribution_in_the_frames():
    _ring, master = in_safeop(1, dc_lock_cycles=5)
    request_op(master, 1)
    run_cycles(master, 50, MS, distribute_time=False)
    assert states(master, 1) == [(0x04, 0)]


def test_sync0_faster_than_the_frames_never_locks():
    _ring, master = in_safeop(1, sync0_ns=MS, dc_lock_cycles=5)
    request_op(master, 1)
    run_cycles(master, 100, 20 * MS)
    assert states(master, 1) == [(0x04, 0)]


def test_frames_faster_than_sync0_lock():
    _ring, master = in_safeop(1, sync0_ns=20 * MS, dc_lock_cycles=5)
    request_op(master, 1)
    run_cycles(master, 30, MS)
    assert states(master, 1) == [(0x08, 0)]


def test_a_50_hz_loop_needs_7_s_to_lock_by_default():
    ring, master = in_safeop(1, sync0_ns=20 * MS)
    request_op(master, 1)
    run_cycles(master, 349, 20 * MS)
    assert states(master, 1) == [(0x04, 0)]
    run_cycles(master, 2, 20 * MS)
    assert states(master, 1) == [(0x08, 0)]
    assert ring.options.dc_lock_cycles * 20 * MS == 7_000 * MS


def test_sync0_cycle_below_500_us_is_refused():
    _ring, master = in_safeop(1, sync0_ns=250_000, dc_lock_cycles=5)
    request_op(master, 1)
    assert states(master, 1) == [(0x14, 0x0035)]


def test_sync0_outrunning_frames_in_op_faults_the_drive_with_4616():
    ring, master = in_op(1)
    enabled = enable_outputs(1, 0x06)
    for controlword in (0x06, 0x07, 0x0F):
        enabled = enable_outputs(1, controlword)
        run_cycles(master, 1, MS, enabled)
    run_cycles(master, 6, 30 * MS, enabled)  # SYNC0 is 10 ms
    _wkc, inputs = run_cycles(master, 1, 30 * MS, enabled)
    assert struct.unpack_from("<H", inputs[0])[0] == 4616
    assert struct.unpack_from("<H", inputs[0], 12)[0] == 0xA000
    assert states(master, 1) == [(0x14, 0x001A)]


def test_free_run_csp_without_dc_faults():
    ring, master = in_safeop(1, sync0_ns=None)
    request_op(master, 1)
    for controlword in (0x06, 0x07, 0x0F):
        _wkc, inputs = run_cycles(master, 1, MS, enable_outputs(1, controlword))
    _wkc, inputs = run_cycles(master, 1, MS, enable_outputs(1, 0x0F))
    assert struct.unpack_from("<H", inputs[0])[0] == 4616


def system_time(master: WireMaster, station: int) -> int:
    return struct.unpack("<Q", master.fprd(station, 0x0910, 8).data)[0]


def time_difference(master: WireMaster, station: int) -> int:
    """0x092C as a signed number: received minus local (bit 31 set when the local copy is the smaller)."""
    raw = struct.unpack("<I", master.fprd(station, 0x092C, 4).data)[0]
    return raw & 0x7FFFFFFF if raw & 0x80000000 else -(raw & 0x7FFFFFFF)


def test_the_time_distribution_shows_how_far_each_clock_is_off_and_a_speed_counter_write_clears_it():
    ring, master = in_safeop(2, sync0_ns=None)
    run_cycles(master, 1, MS)
    assert time_difference(master, 0x1002) == 700  # latched one hop after the reference, so that far behind
    offset = struct.unpack("<Q", master.fprd(0x1002, 0x0920, 8).data)[0]
    master.fpwr(0x1002, 0x0920, struct.pack("<Q", offset - 5_000))
    run_cycles(master, 1, MS)
    assert time_difference(master, 0x1002) == 5_700
    assert struct.unpack("<I", master.fprd(0x1002, 0x092C, 4).data)[0] & 0x80000000  # the local copy is smaller
    master.fpwr(0x1002, 0x0920, struct.pack("<Q", offset + 3_000))
    run_cycles(master, 1, MS)
    assert time_difference(master, 0x1002) == -2_300
    speed = master.fprd(0x1002, 0x0930, 2).data
    assert speed == struct.pack("<H", 0x1000)
    master.fpwr(0x1002, 0x0930, speed)
    assert master.fprd(0x1002, 0x092C, 4).data == bytes(4)


def test_a_slave_back_from_a_power_cycle_stays_out_of_step_until_the_master_sets_its_clock_again():
    ring, master = in_op(2)
    ring.lose(1)
    ring.restore(1)
    master.set_station_addresses()
    master.program_mailbox(0x1002)
    master.request_state(0x1002, 0x02)
    master.map_pdos(0x1002)
    master.program_process_data(1)
    master.request_state(0x1002, 0x04)
    assert system_time(master, 0x1002) < 10**12  # its clock started again, with no offset
    master.start_sync0(0x1002, 10 * MS)
    master.request_state(0x1002, 0x08)
    run_cycles(master, 20, MS)
    assert states(master, 2) == [(0x08, 0), (0x04, 0)]  # its OP request waits: SYNC0 on its own time never locks
    assert time_difference(master, 0x1002) == 0x7FFFFFFF  # saturated, and behind
    assert ring.slaves[1].lock_count == 0
    own = struct.unpack("<Q", master.fprd(0x1002, 0x0920, 8).data)[0]
    master.fpwr(0x1002, 0x0920, struct.pack("<Q", own + system_time(master, 0x1001) - system_time(master, 0x1002)))
    master.start_sync0(0x1002, 10 * MS)
    run_cycles(master, 10, MS)
    assert abs(time_difference(master, 0x1002)) < 1_000
    assert states(master, 2) == [(0x08, 0), (0x08, 0)]


def test_a_reference_clock_that_starts_again_from_zero_throws_the_others_out_of_step():
    ring, master = in_op(3)
    ring.lose(0)
    ring.restore(0)
    master.set_station_addresses()  # the time distribution reads the reference's fresh clock again
    run_cycles(master, 4, MS)
    assert states(master, 3)[1:] == [(0x08, 0), (0x08, 0)]
    run_cycles(master, 1, MS)  # the fifth frame in a row that far off
    assert states(master, 3)[1:] == [(0x14, 0x001A), (0x14, 0x001A)]
    assert not ring.slaves[1].locked and not ring.slaves[2].locked


def test_mailbox_traffic_during_dc_activation_faults_with_0xa000():
    ring, master = in_safeop(2, dc_lock_cycles=50)
    request_op(master, 2)
    run_cycles(master, 10, MS)
    master.mailbox_write(0x1002, struct.pack("<HBHBI", 0x2000, 0x40, 0x1018, 1, 0))
    assert ring.slaves[1].drive.error_code.value == 0xA000
    assert ring.slaves[0].drive.error_code.value == 0
    assert ring.slaves[1].lock_count == 0


def test_mailbox_traffic_after_lock_is_harmless():
    ring, master = in_op(1)
    master.mailbox_write(0x1001, struct.pack("<HBHBI", 0x2000, 0x40, 0x1018, 1, 0))
    assert ring.slaves[0].drive.error_code.value == 0


# ---- watchdog and faults ----------------------------------------------------------------------------------------
def test_outputs_missing_for_100_ms_drop_the_slave_to_safeop_with_0x001b():
    ring, master = in_op(1)
    master.now_ns += 101 * MS
    ring.advance(master.now_ns)
    assert states(master, 1) == [(0x14, 0x001B)]


def test_leaving_op_while_enabled_faults_the_drive_with_0xa000():
    ring, master = in_op(1)
    for controlword in (0x06, 0x07, 0x0F):
        run_cycles(master, 1, MS, enable_outputs(1, controlword))
    master.request_state(0x1001, 0x04)
    assert ring.slaves[0].drive.error_code.value == 0xA000


def test_lost_slave_ends_the_line():
    ring, master = make(4)
    ring.lose(2)
    assert master.brd(0x0000, 2).wkc == 2
    assert ring.slaves[1].esc.mem[0x0111] & 0x04  # slave 1 closed port 1


def test_restored_slave_comes_back_in_init_without_address():
    ring, master = make(3)
    master.set_station_addresses()
    ring.lose(1)
    ring.restore(1)
    assert master.brd(0x0000, 2).wkc == 3
    assert ring.slaves[1].esc.station_address == 0
    assert ring.slaves[2].esc.station_address == 0x1003


# ---- mailbox mechanics ------------------------------------------------------------------------------------------
def test_reading_an_empty_mailbox_is_refused():
    ring, master = in_safeop(1, sync0_ns=None)
    assert master.fprd(0x1001, 0x1080, 128).wkc == 0


def test_reply_appears_after_the_mailbox_latency():
    ring, master = in_safeop(1, sync0_ns=None, mailbox_latency_s=0.002)
    master.mailbox_write(0x1001, struct.pack("<HBHBI", 0x2000, 0x40, 0x1018, 1, 0))
    assert master.mailbox_read(0x1001) is None
    master.now_ns += 2 * MS
    reply = master.mailbox_read(0x1001)
    assert struct.unpack_from("<I", reply, 12)[0] == 0x5A65726F


def test_write_mailbox_refuses_a_second_request_while_full():
    ring, master = in_safeop(1, sync0_ns=None)
    ring.slaves[0].esc._set_mailbox_full(0, True)
    assert master.mailbox_write(0x1001, b"\x00" * 10).wkc == 0


def test_repeat_request_offers_the_last_reply_again():
    ring, master = in_safeop(1, sync0_ns=None, mailbox_latency_s=0.0)
    master.mailbox_write(0x1001, struct.pack("<HBHBI", 0x2000, 0x40, 0x1018, 1, 0))
    first = master.mailbox_read(0x1001)
    assert master.mailbox_read(0x1001) is None
    master.fpwr(0x1001, 0x080E, b"\x03")  # enable + toggled repeat request
    assert master.fprd(0x1001, 0x080F, 1).data[0] & 0x02
    assert master.mailbox_read(0x1001) == first


UPLOAD_IDENTITY = struct.pack("<HBHBI", 0x2000, 0x40, 0x1018, 1, 0)


def reply_after(master: WireMaster, limit_ms: int) -> int | None:
    """Emulated ms until the request's reply shows in the read mailbox (None: not within ``limit_ms``)."""
    for waited in range(limit_ms + 1):
        if master.mailbox_read(0x1001) is not None:
            return waited
        master.now_ns += MS
        master.ring.advance(master.now_ns)
    return None


def test_a_scripted_late_reply_comes_that_much_later_and_the_next_one_on_time():
    ring, master = in_safeop(1, sync0_ns=None, mailbox_latency_s=0.001)
    ring.latency.script(1, 0.008)
    master.mailbox_write(0x1001, UPLOAD_IDENTITY)
    assert reply_after(master, 20) == 9
    master.mailbox_write(0x1001, UPLOAD_IDENTITY)
    assert reply_after(master, 20) == 1


def test_a_burst_slows_that_many_replies_then_the_drive_answers_on_time_again():
    ring, master = in_safeop(1, sync0_ns=None, mailbox_latency_s=0.001, mailbox_burst_s=0.005,
                             mailbox_burst_replies=2)
    waits = []
    for chance in (1.0, 0.0, 0.0, 0.0):  # the first reply starts a burst, then none does
        ring.options.mailbox_burst_chance = chance
        master.mailbox_write(0x1001, UPLOAD_IDENTITY)
        waits.append(reply_after(master, 20))
    assert waits == [6, 6, 1, 1]


def test_jitter_keeps_each_reply_within_latency_plus_jitter_and_the_same_seed_repeats_a_run():
    def waits(seed: int) -> list[int | None]:
        _ring, master = in_safeop(1, sync0_ns=None, mailbox_latency_s=0.001, mailbox_jitter_s=0.010, seed=seed)
        out = []
        for _ in range(8):
            master.mailbox_write(0x1001, UPLOAD_IDENTITY)
            out.append(reply_after(master, 30))
        return out

    first = waits(7)
    assert all(w is not None and 1 <= w <= 11 for w in first) and len(set(first)) > 1
    assert waits(7) == first


def test_a_read_mailbox_switched_off_above_init_drops_the_slave_to_init_with_0x0016():
    # what SOEM's repeat request writes when it toggles a stale copy of SM1's status word: enable bit clear
    ring, master = in_safeop(1, sync0_ns=None)
    master.fpwr(0x1001, 0x080D, b"\x0a\x02")
    assert master.al_status(0x1001) == (0x11, 0x0016)
    master.mailbox_write(0x1001, UPLOAD_IDENTITY)
    assert reply_after(master, 5) is None


def test_a_repeat_request_with_the_mailbox_left_enabled_keeps_the_slave_where_it_was():
    ring, master = in_safeop(1, sync0_ns=None)
    master.fpwr(0x1001, 0x080D, b"\x00\x03")
    assert master.al_status(0x1001) == (0x04, 0)


# ---- process data moves the drive -------------------------------------------------------------------------------
def test_process_data_enables_the_drive_and_tracks_the_target():
    ring, master = in_op(1)
    ring.plant.gravity[:] = 0.0
    for controlword in (0x06, 0x07, 0x0F):
        run_cycles(master, 1, MS, enable_outputs(1, controlword))
    target = 8000  # counts, about 0.096 rad
    _wkc, inputs = run_cycles(master, 1500, MS, enable_outputs(1, 0x0F, target))
    statusword, position = struct.unpack_from("<Hi", inputs[0])
    assert statusword == 5687
    assert position == pytest.approx(target, abs=40)


def test_lrw_leaves_the_output_bytes_of_the_frame_unchanged():
    ring, master = in_op(2)
    outputs = [RXPDO_STRUCT.pack(0x06, 1234, 0, 0, 8), RXPDO_STRUCT.pack(0x06, 5678, 0, 0, 8)]
    master.now_ns += MS
    image = b"".join(outputs) + bytes(TXPDO_STRUCT.size * 2)
    reply = master.exchange([Datagram.logical(Command.LRW, 0, image)])[0]
    assert reply.data[:2 * RXPDO_STRUCT.size] == b"".join(outputs)


def test_mujoco_plant_follows_the_drive_on_the_arm():
    ring, master = in_op(10, plant="mujoco")
    outputs = [IDLE_OUTPUT] * 10
    for controlword in (0x06, 0x07, 0x0F):
        outputs[3] = RXPDO_STRUCT.pack(controlword, 0, 0, 0, 8)
        run_cycles(master, 1, MS, outputs)
    target = -40000  # left elbow pitch, about -0.48 rad
    outputs[3] = RXPDO_STRUCT.pack(0x0F, target, 0, 0, 8)
    _wkc, inputs = run_cycles(master, 1000, MS, outputs)
    statusword, position = struct.unpack_from("<Hi", inputs[3])
    assert statusword == 5687
    assert position == pytest.approx(target, rel=0.02)


# ---- PDO mapping over SDO --------------------------------------------------------------------------------
def in_preop(**options: object) -> tuple[Ring, WireMaster]:
    ring, master = make(1, mailbox_latency_s=0.0, **options)
    master.set_station_addresses()
    master.program_mailbox(0x1001)
    master.request_state(0x1001, 0x12)
    return ring, master


def test_a_drive_powers_up_with_zeroerr_s_mapping_not_prime_s():
    _ring, master = in_preop()

    def entries(mapping: int) -> list[int]:
        count = master.sdo_upload(0x1001, mapping, 0)[0]
        return [struct.unpack("<I", master.sdo_upload(0x1001, mapping, sub))[0] for sub in range(1, count + 1)]

    assert entries(0x1600) == [0x607A0020, 0x60FE0020, 0x60400010] == [e.mapping for e in POWER_UP_RXPDO]
    assert entries(0x1A00) == [0x60640020, 0x60FD0020, 0x60410010] == [e.mapping for e in POWER_UP_TXPDO]


def test_sm_sized_for_prime_s_layout_is_refused_until_the_pdos_are_remapped():
    _ring, master = in_preop()
    master.program_process_data(0)  # SM2/SM3 sized for Prime's 14/16 bytes
    master.request_state(0x1001, 0x04)
    assert master.al_status(0x1001) == (0x12, 0x001D)  # invalid output configuration
    master.request_state(0x1001, 0x12)
    master.map_pdos(0x1001)
    master.request_state(0x1001, 0x04)
    assert master.al_status(0x1001) == (0x04, 0)


def test_mapping_entries_change_only_while_the_count_is_zero():
    _ring, master = in_preop()
    reply = master.sdo_download(0x1001, 0x1A00, 1, struct.pack("<I", 0x60410010))
    assert sdo_abort_code(reply) == 0x06010003


def test_mapping_an_output_object_into_the_txpdo_is_refused():
    _ring, master = in_preop()
    master.sdo_download(0x1001, 0x1A00, 0, b"\x00")
    master.sdo_download(0x1001, 0x1A00, 1, struct.pack("<I", 0x60400010))  # controlword is an RxPDO object
    assert sdo_abort_code(master.sdo_download(0x1001, 0x1A00, 0, b"\x01")) == 0x06040041


def test_mapping_cannot_change_outside_preop():
    ring, master = in_safeop(1, sync0_ns=None, mailbox_latency_s=0.0)
    assert sdo_abort_code(master.sdo_download(0x1001, 0x1A00, 0, b"\x00")) == 0x08000022


def test_remapped_inputs_fill_sm3_in_the_new_order():
    ring, master = in_preop()
    master.sdo_download(0x1001, 0x1A00, 0, b"\x00")
    master.sdo_download(0x1001, 0x1A00, 1, struct.pack("<I", 0x60640020))  # position actual first
    master.sdo_download(0x1001, 0x1A00, 2, struct.pack("<I", 0x60410010))
    master.sdo_download(0x1001, 0x1A00, 0, b"\x02")
    rx_size = sum(e.bits for e in POWER_UP_RXPDO) // 8  # the outputs still in ZeroErr's power-up layout
    master.fpwr(0x1001, 0x0810, struct.pack("<HHI", 0x1100, rx_size, 0x00010064))
    master.fpwr(0x1001, 0x0818, struct.pack("<HHI", 0x1180, 6, 0x00010020))
    master.request_state(0x1001, 0x04)
    assert master.al_status(0x1001) == (0x04, 0)
    ring.plant.q[0] = 0.5
    master.now_ns += MS
    ring.advance(master.now_ns)
    position, statusword = struct.unpack("<iH", master.fprd(0x1001, 0x1180, 6).data)
    assert (position, statusword) == (round(0.5 * COUNTS_PER_RAD), 0x0250)


# ---- time -------------------------------------------------------------------------------------------------------
def test_behind_real_time_the_physics_catches_up_at_most_max_steps_per_call():
    ring, master = make(1, physics_dt_s=0.001)
    steps = []
    step = ring.plant.step
    ring.plant.step = lambda *args: (steps.append(1), step(*args))
    master.now_ns += 10 * MS  # a stalled host: ten physics steps are due
    assert ring.advance(master.now_ns, max_steps=3) is False
    assert len(steps) == 3
    while not ring.advance(master.now_ns, max_steps=3):
        pass
    assert len(steps) == 10
    assert ring.advance(master.now_ns) is True and len(steps) == 10
