"""SOEM (through pysoem) against the emulated ring on a veth pair: the master cannot tell it from drives.

Needs a private network namespace (root, or the test run under ``unshare -rn``); skipped otherwise."""

from __future__ import annotations

import json
import os
import socket
import struct

import pytest

from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD, PRODUCT_CODE, VENDOR_ID
from humanoid_prime.drivers.erob.objects import MAPPING_WRITES, RXPDO_STRUCT, TXPDO, TXPDO_STRUCT
from humanoid_prime.virtual.netns import EmulatedRing, netns_unavailable_reason
from humanoid_prime.virtual.ring.control import ControlError

pysoem = pytest.importorskip("pysoem")
_REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(_REASON is not None, reason=_REASON or "")]

SLAVES = 10
LOCK_CYCLES = 30
SYNC0_NS = 10_000_000
PERIOD_S = 0.001


@pytest.fixture(scope="module")
def ring():
    with EmulatedRing(slaves=SLAVES, dc_lock_cycles=LOCK_CYCLES) as emulated:
        yield emulated


@pytest.fixture
def master(ring):
    master = pysoem.Master()
    master.open(ring.master_interface)
    yield master
    master.close()


def exchange(master) -> int:
    """One process-data exchange. The wait (40 ms) is twenty times SOEM's default so that an emulator on a loaded
    machine still answers in it (these tests judge what comes back, not how fast), and well inside the drives' 100 ms
    output watchdog, so that a frame lost on purpose costs one exchange and not the slaves' OP."""
    master.send_processdata()
    return master.receive_processdata(40_000)


def map_prime_pdos(master) -> None:
    """Prime's PDO mapping written in SOEM's PRE-OP -> SAFE-OP hook, as SoemMaster does."""
    for slave in master.slaves:
        def hook(position: int, slave=slave) -> None:
            for index, sub, data in MAPPING_WRITES:
                slave.sdo_write(index, sub, data)
        slave.config_func = hook


def to_op(master, max_cycles: int = 20_000) -> int:
    """Prime's mapping, ec_config_map, ec_configdc, SYNC0 on every slave, then a 1 kHz loop until all slaves are
    in OP; returns the cycles it took (bounded in cycles, not in wall time)."""
    map_prime_pdos(master)
    master.config_map()
    assert master.state_check(pysoem.SAFEOP_STATE, 500_000) == pysoem.SAFEOP_STATE
    assert master.config_dc()
    for slave in master.slaves:
        slave.dc_sync(True, SYNC0_NS)
    master.state = pysoem.OP_STATE
    master.write_state()
    rate = Rate(1.0 / PERIOD_S)
    for cycle in range(max_cycles):
        rate.wait()
        exchange(master)
        if master.read_state() == pysoem.OP_STATE:
            return cycle
    raise AssertionError(f"not in OP after {max_cycles} cycles: {[hex(s.state) for s in master.slaves]}")


def test_config_init_finds_every_erob_with_its_identity(master):
    assert master.config_init() == SLAVES
    assert [(s.man, s.id) for s in master.slaves] == [(VENDOR_ID, PRODUCT_CODE)] * SLAVES
    assert master.slaves[0].name == "eRob CiA402 (emulated)"
    assert master.state_check(pysoem.PREOP_STATE, 500_000) == pysoem.PREOP_STATE


def test_config_map_alone_finds_zeroerr_s_power_up_mapping(master):
    master.config_init()
    assert master.config_map() == SLAVES * (10 + 10)  # 607A 60FE 6040 / 6064 60FD 6041
    assert [(len(s.output), len(s.input)) for s in master.slaves] == [(10, 10)] * SLAVES


def test_config_map_after_the_remap_maps_14_output_and_16_input_bytes_per_drive(master):
    master.config_init()
    map_prime_pdos(master)
    assert master.config_map() == SLAVES * (RXPDO_STRUCT.size + TXPDO_STRUCT.size)
    assert [(len(s.output), len(s.input)) for s in master.slaves] == [(14, 16)] * SLAVES
    assert master.expected_wkc == 3 * SLAVES


def test_drives_reach_op_after_the_dc_lock_and_count_in_the_working_counter(master):
    master.config_init()
    assert to_op(master) >= LOCK_CYCLES
    assert exchange(master) == master.expected_wkc


def test_sdo_write_of_the_position_gain_round_trips(master, ring):
    master.config_init()
    slave = master.slaves[3]
    since = len(ring.control.sdo_log())
    slave.sdo_write(0x2383, 0, struct.pack("<I", 1))  # UDINT
    with pytest.raises(pysoem.SdoError) as error:
        slave.sdo_write(0x2382, 1, struct.pack("<I", 777))  # four bytes into an UNSIGNED16: refused, not applied
    assert error.value.abort_code == 0x06070010
    slave.sdo_write(0x2382, 1, struct.pack("<H", 777))
    assert slave.sdo_read(0x2382, 1) == struct.pack("<H", 777)
    log = ring.control.sdo_log(since)
    assert [(e["position"], e["index"], e["sub"], e["value"], e["applied"]) for e in log] == [
        (3, 0x2383, 0, 1, True), (3, 0x2382, 1, 777, True)]
    assert ring.control.slave(3)["drive"]["pos_reg"] == 777


def test_sdo_abort_reaches_the_master_with_its_code(master):
    master.config_init()
    with pytest.raises(pysoem.SdoError) as error:
        master.slaves[0].sdo_read(0x2999, 0)
    assert error.value.abort_code == 0x06020000


def test_pysoem_reads_the_object_dictionary_through_sdo_information(master):
    master.config_init()
    od = {obj.index: obj for obj in master.slaves[1].od}
    assert {0x1000, 0x1018, 0x2381, 0x2382, 0x2383, 0x6064, 0x6076, 0x6502} <= set(od)
    gains = od[0x2382]
    assert (gains.name, gains.object_code) == (b"Position Loop Gains", 8)
    assert [(e.name, e.data_type, e.bit_length) for e in gains.entries] == [
        (b"Number of entries", 5, 8), (b"Position Loop Proportional Gain", 6, 16),
        (b"Position Loop integral Gain", 6, 16)]
    assert (od[0x6076].data_type, od[0x6076].bit_length) == (7, 32)  # rated torque, UNSIGNED32
    assert od[0x6076].obj_access & 0x0080  # TxPDO mappable


def test_a_second_master_session_finds_the_mailbox_empty(ring):
    """A session that leaves a reply behind (here: a repeat request after its last SDO) must not hand it to
    the next master, which may not flush the mailbox before its first request."""
    first = pysoem.Master()
    first.open(ring.master_interface)
    try:
        first.config_init()
        slave = first.slaves[2]
        assert slave.sdo_read(0x1000, 0) == struct.pack("<I", 0x00020192)  # the last reply: device type
        # private to pysoem: _fprd/_fpwr, its only raw register access, read the mailbox SyncManager's own state
        ack = slave._fprd(0x080E, 1)[0]
        slave._fpwr(0x080E, bytes([ack ^ 0x02]))  # repeat request: the reply is offered again ...
        for _ in range(1000):
            if slave._fprd(0x080D, 1)[0] & 0x08:
                break
        assert slave._fprd(0x080D, 1)[0] & 0x08, "the repeated reply never arrived"
    finally:
        first.close()  # ... and left unread
    second = pysoem.Master()
    second.open(ring.master_interface)
    try:
        assert second.config_init() == SLAVES
        assert not second.slaves[2]._fprd(0x080D, 1)[0] & 0x08  # SM1 empty (private to pysoem: see above)
        assert second.slaves[2].sdo_read(0x6502, 0) == struct.pack("<I", 0x38D)  # its own answer, not the old one
    finally:
        second.close()


def next_controlword(statusword: int) -> int:
    """Shutdown from switch-on disabled, switch on from ready, enable from switched on."""
    if statusword & 0x4F == 0x40:
        return 0x06
    return 0x07 if statusword & 0x6F == 0x21 else 0x0F


def test_process_data_moves_a_drive(master, ring):
    master.config_init()
    to_op(master)
    drive = master.slaves[4]
    before = ring.control.slave(4)["joint"]["q_rad"]
    target = struct.unpack_from("<i", bytes(drive.input), 2)[0]
    step = round(0.3 * COUNTS_PER_RAD / 1000)  # 0.3 rad over 1000 cycles once enabled
    rate = Rate(1.0 / PERIOD_S)
    moved = 0
    for _ in range(20_000):  # enabling takes a few cycles, then 1000 cycles of motion and 500 to settle
        if moved >= 1500:
            break
        rate.wait()
        statusword = struct.unpack_from("<H", bytes(drive.input))[0]
        if statusword == 5687:
            moved += 1
            if moved <= 1000:
                target += step
        drive.output = RXPDO_STRUCT.pack(next_controlword(statusword), target, 0, 0, 8)
        exchange(master)
    status = ring.control.slave(4)
    assert status["drive"]["statusword"] == 5687
    assert status["joint"]["q_rad"] - before == pytest.approx(0.3, abs=0.03)


def test_remapped_txpdo_is_honoured(master):
    master.config_init()

    def drop_torque(position: int) -> None:
        slave = master.slaves[position]
        entries = [e for e in TXPDO if e.index != 0x6077]
        slave.sdo_write(0x1A00, 0, b"\x00")
        for sub, entry in enumerate(entries, 1):
            slave.sdo_write(0x1A00, sub, struct.pack("<I", entry.mapping))
        slave.sdo_write(0x1A00, 0, bytes([len(entries)]))

    master.slaves[1].config_func = drop_torque
    master.config_map()
    assert len(master.slaves[1].input) == TXPDO_STRUCT.size - 2
    assert master.state_check(pysoem.SAFEOP_STATE, 500_000) == pysoem.SAFEOP_STATE


def test_long_object_arrives_by_segmented_upload():
    with EmulatedRing(slaves=1, mailbox_size=48) as small:
        master = pysoem.Master()
        master.open(small.master_interface)
        try:
            master.config_init()
            assert master.slaves[0].sdo_read(0x1008, 0) == b"eRob rotary actuator, CiA402 (emulated)"
        finally:
            master.close()


def test_lost_slave_shortens_the_ring_the_master_finds(master, ring):
    ring.control.lose_slave(7)
    try:
        assert master.config_init() == 7
    finally:
        ring.control.restore_slave(7)
    assert master.config_init() == SLAVES


def test_harness_removes_the_veth_pair_on_exit():
    with EmulatedRing(slaves=1) as emulated:
        interface = emulated.master_interface
        assert os.path.exists(f"/sys/class/net/{interface}")
    assert not os.path.exists(f"/sys/class/net/{interface}")


def test_harness_removes_the_veth_pair_when_the_body_raises():
    with pytest.raises(RuntimeError), EmulatedRing(slaves=1) as emulated:
        interface = emulated.master_interface
        pid = emulated.pid
        raise RuntimeError("test body failed")
    assert not os.path.exists(f"/sys/class/net/{interface}")
    assert not os.path.exists(f"/proc/{pid}")


def test_control_refuses_an_unknown_slave(ring):
    with pytest.raises(ControlError, match="no slave at ring position 99"):
        ring.control.slave(99)


def test_control_refuses_a_request_that_is_no_json_object_and_serves_on(ring):
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as client:
        client.settimeout(5.0)
        client.connect(ring.control.path)
        client.sendall(b'"status"\n')
        reply = client.makefile("rb").readline()
    assert json.loads(reply) == {"ok": False, "error": "a request is a JSON object, got '\"status\"'"}
    ring.control.ping()


def in_op(master) -> None:
    master.config_init()
    to_op(master)


def test_a_dropped_frame_costs_one_cycle(master, ring):
    in_op(master)
    ring.control.drop_frames(1)
    assert exchange(master) == -1  # SOEM's EC_NOFRAME
    assert exchange(master) == master.expected_wkc


def test_junk_frames_between_replies_do_not_disturb_the_master(master, ring):
    in_op(master)
    ring.control.garbage_frames(5)
    assert [exchange(master) for _ in range(5)] == [master.expected_wkc] * 5


def test_a_silent_slave_stops_answering_sdo_and_serves_it_when_it_wakes(master, ring):
    master.config_init()
    master.sdo_read_timeout = 50_000
    ring.control.silence(2)
    try:
        with pytest.raises(pysoem.WkcError):
            master.slaves[2].sdo_read(0x1018, 1)
    finally:
        ring.control.silence(2, False)
    assert struct.unpack("<I", master.slaves[2].sdo_read(0x1018, 1))[0] == VENDOR_ID


def test_responder_reports_its_turnaround(ring):
    stats = ring.control.stats()
    assert stats["frames"] > 0
    assert stats["turnaround_median_us"] > 0


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to keep one free")
def test_an_emulator_told_to_avoid_the_loops_cpu_runs_on_the_others():
    loop_cpu = min(os.sched_getaffinity(0))
    others = set(os.sched_getaffinity(0)) - {loop_cpu}
    with EmulatedRing(slaves=2, avoid_cpu=loop_cpu) as emulated:
        emulated.control.ping()  # up and serving, every thread started
        threads = os.listdir(f"/proc/{emulated.pid}/task")
        assert {tid: os.sched_getaffinity(int(tid)) for tid in threads} == {tid: others for tid in threads}
