"""The SOEM master and EthercatSystem against ten emulated eRob on a veth pair (DESIGN §4.2)."""

from __future__ import annotations

import contextlib
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from doubles.sockets import frame_elsewhere_at_each_bind
from humanoid_prime.config.calibration import JointCalibration, load_calibration
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD
from humanoid_prime.drivers.erob.objects import BUS_GAIN_GATE, ERROR_CODE, POS_LOOP_GAIN, VEL_LOOP_GAIN
from humanoid_prime.drivers.ethercat.errors import SdoError, SdoRefused
from humanoid_prime.drivers.ethercat.link import Channel, SocketWire, brd, build_frame, frame_index
from humanoid_prime.drivers.ethercat.mailbox import CoeMailbox, MailboxLayout
from humanoid_prime.drivers.ethercat.ring import expected_ring
from humanoid_prime.drivers.ethercat.sdo_client import SizedSdo
from humanoid_prime.drivers.ethercat.soem_contract import SocketWatch
from humanoid_prime.drivers.ethercat.soem_master import SoemMaster
from humanoid_prime.drivers.ethercat.system import EthercatSystem
from humanoid_prime.virtual.netns import EmulatedRing, netns_unavailable_reason
from humanoid_prime.virtual.ring.firmware import MAILBOX_IN_START, MAILBOX_OUT_START

REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(REASON is not None, reason=f"no emulated ring: {REASON}")]

UPDATE_RATE = 50.0


def wait_for(condition, timeout_s: float = 30.0, what: str = "condition") -> None:
    """Waits for ``condition``; the bound only ends a test that would hang, so it allows a loaded machine."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not reached within {timeout_s} s")
        time.sleep(0.01)


class Loop:
    """The controller manager's part: read() then write() at the update rate, in a thread."""

    def __init__(self, system: EthercatSystem, n: int) -> None:
        self.system = system
        self.command = CommandArrays(n)
        self.state = StateArrays(n)
        self.ticks = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        rate = Rate(UPDATE_RATE, sleep=self._stop.wait)
        while not self._stop.is_set():
            rate.wait()
            self.system.read(0.0, self.state)
            self.system.write(0.0, self.command)
            self.ticks += 1

    def __enter__(self) -> Loop:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


@pytest.fixture
def ring():
    with EmulatedRing(slaves=10) as r:
        yield r


def make_system(robot, ring, calibration=None, **master_options) -> EthercatSystem:
    master = SoemMaster(ring.master_interface, update_rate=UPDATE_RATE, bringup_rate=1000.0,
                        **master_options)
    system = EthercatSystem(robot, calibration or load_calibration(robot.hardware), update_rate=UPDATE_RATE,
                            master=master)
    return system


@pytest.fixture
def system(robot, ring):
    cal = load_calibration(robot.hardware).with_joint("left_wrist_yaw", JointCalibration(-1, 0.3))
    s = make_system(robot, ring, cal)
    s.configure()
    s.activate()
    yield s
    s.shutdown()


def test_ten_emulated_erob_reach_op_and_operation_enabled(system, ring):
    status = ring.control.status()
    assert [s["al_state"] for s in status] == ["OP"] * 10
    assert [s["drive"]["statusword"] for s in status] == [5687] * 10
    assert system.master.expected_wkc == 30


def test_soem_drops_prime_s_replies_in_its_socket_and_reads_it_before_they_could_fill_it(system, ring, robot):
    """SOEM's socket gets a copy of every reply to Prime's frames; SOEM drops them when it reads its socket, and the
    master has it read before QUEUE_LIMIT of them queue there: no cycle frame is lost to a full queue."""
    master = system.master
    with Loop(system, robot.n) as loop:
        wait_for(lambda: loop.ticks >= 5, what="the loop ticking")
        before, drains = system.wkc_errors, master.queue.drains
        with ThreadPoolExecutor(10) as pool:
            list(pool.map(lambda k: [master.sdo_read(k, ERROR_CODE, 0) for _ in range(30)], range(10)))
        ticks = loop.ticks
        wait_for(lambda: loop.ticks >= ticks + 5, what="more ticks")
    assert master.queue.drains > drains  # 300 transfers, several frames each: SOEM was made to read its socket
    # A queue that filled would lose cycle replies; one missed cycle is what a stall of this VM longer than SOEM's
    # 2 ms frame timeout costs the loop thread (it shares the interpreter with ten SDO threads here). (Without the
    # keeper this traffic rarely fills the queue on a veth pair: the drains above are what show the keeper works.)
    assert system.wkc_errors - before <= 1
    assert master.mailbox_drops() == {"late": 0, "other object": 0, "unrecognised": 0, "malformed": 0}


def test_each_joint_commands_and_reads_its_own_ring_position(system, ring, robot):
    cal = system.calibration
    targets = {joint: 0.03 * (position + 1) for joint, position in robot.hardware.erob_slaves.items()}

    def raw(joint: str, q: float) -> float:
        return cal.joints[joint].direction * q + cal.joints[joint].homing_offset

    with Loop(system, robot.n) as loop:
        for joint, q in targets.items():
            loop.command.position[robot.index(joint)] = q
            loop.command.stiffness[robot.index(joint)] = 20.0
        wait_for(lambda: loop.ticks > 5, what="five ticks")
        status = ring.control.status()
        for joint, position in robot.hardware.erob_slaves.items():
            assert status[position]["drive"]["target_position"] == math.floor(
                raw(joint, targets[joint]) * COUNTS_PER_RAD + 0.5), joint

        def settled() -> bool:
            status = ring.control.status()
            return all(abs(loop.state.position[robot.index(joint)] - cal.joints[joint].direction * (
                status[position]["drive"]["position_actual"] / COUNTS_PER_RAD - cal.joints[joint].homing_offset))
                < 1e-3 for joint, position in robot.hardware.erob_slaves.items())

        wait_for(settled, what="every joint reading its own drive")


def test_a_commanded_position_reaches_the_drive_through_factor_and_offset_and_reads_back(system, ring, robot):
    j = robot.index("left_wrist_yaw")
    position = robot.hardware.erob_slaves["left_wrist_yaw"]
    with Loop(system, robot.n) as loop:
        wait_for(lambda: loop.ticks > 2, what="two ticks")
        loop.command.position[j] = loop.state.position[j]
        loop.command.stiffness[j] = 20.0
        time.sleep(0.1)
        loop.command.position[j] = 0.2
        wait_for(lambda: ring.control.slave(position)["drive"]["target_position"]
                 == math.floor(-0.2 * COUNTS_PER_RAD + 0.3 * COUNTS_PER_RAD + 0.5), what="target at the drive")
        wait_for(lambda: abs(loop.state.position[j] - 0.2) < 0.01, what="joint at 0.2 rad")
    raw = ring.control.slave(position)["drive"]["position_actual"] / COUNTS_PER_RAD
    assert raw == pytest.approx(-0.2 + 0.3, abs=0.01)  # q_raw = direction*q + homing_offset


def test_zero_stiffness_keeps_the_drive_target_on_the_actual_position(system, ring, robot):
    ring.control.set_joint(2, 0.4)
    with Loop(system, robot.n) as loop:
        loop.command.position[:] = -1.0  # far away, but limp: must not be followed
        wait_for(lambda: loop.ticks > 5, what="five ticks")
        drive = ring.control.slave(2)["drive"]
    assert abs(drive["target_position"] - drive["position_actual"]) < 0.001 * COUNTS_PER_RAD
    assert drive["error_code"] == 0


def test_the_products_bringup_never_faults_a_drive_with_0xa000(system, ring):
    status = ring.control.status()
    assert [s["mailbox_faults"] for s in status] == [0] * 10
    assert [s["drive"]["error_history"] for s in status] == [[]] * 10


def test_an_sdo_before_op_is_refused_by_the_master(robot, ring):
    master = SoemMaster(ring.master_interface, update_rate=UPDATE_RATE)
    with master:
        master.open()
        with pytest.raises(SdoRefused, match="0xA000"):
            master.sdo_read(0, ERROR_CODE, 0)
    assert [s["mailbox_faults"] for s in ring.control.status()] == [0] * 10


def test_an_sdo_during_dc_activation_faults_the_drive_with_0xa000(robot):
    """The reason the master refuses SDOs before OP: another master's request, straight into a drive's mailbox while
    its DC locks, faults it with 0xA000."""
    with EmulatedRing(slaves=10, dc_lock_cycles=3000) as ring:  # 3 s at 1 kHz to lock: a wide window
        master = SoemMaster(ring.master_interface, update_rate=UPDATE_RATE, bringup_rate=1000.0)
        with master:
            bringup = threading.Thread(target=master.start, args=(expected_ring(robot.hardware.erob_slaves),))
            bringup.start()
            wait_for(lambda: (slave := ring.control.slave(2))["al_state"] == "SAFE-OP" and slave["dc"]["sync0_running"],
                     timeout_s=20, what="SYNC0 running on ring 2 in SAFE-OP")
            other = Channel(SocketWire(ring.master_interface, 0xF8, 0xFF), range(0xF8, 0x100))
            try:
                mailbox = CoeMailbox(other, 2, 0x1003, MailboxLayout(MAILBOX_OUT_START, 128, MAILBOX_IN_START, 128))
                with contextlib.suppress(SdoError):
                    mailbox.upload(ERROR_CODE, 0, 0.1)
            finally:
                other.close()
            bringup.join(30)
            for _ in range(200):  # the drive reports CSP (bit 12 of 4616) once it has seen mode 8 in OP
                master.exchange()
                if int(master.inputs["statusword"][2]) == 4616:
                    break
            slave = ring.control.slave(2)
            assert slave["mailbox_faults"] == 1
            assert slave["drive"]["error_code"] == 0xA000
            assert int(master.inputs["statusword"][2]) == 4616
            assert int(master.inputs["error_code"][2]) == 0xA000
            assert [s["mailbox_faults"] for s in ring.control.status() if s["position"] != 2] == [0] * 9


def test_a_sync0_that_differs_from_the_loop_is_refused_before_the_ring_is_touched(ring):
    with pytest.raises(Exception, match="never locks.*4616"):
        SoemMaster(ring.master_interface, update_rate=UPDATE_RATE, sync0_period_s=0.005)
    assert [s["al_state"] for s in ring.control.status()] == ["INIT"] * 10


def test_a_forced_sync0_faster_than_the_loop_faults_the_drives_with_4616(robot, ring):
    system = make_system(robot, ring)
    system.master.sync0_ns = 5_000_000  # what no setting can give: a SYNC0 four times the frame rate
    system.configure()
    system.activate()
    try:
        with Loop(system, robot.n) as loop:
            wait_for(lambda: "ethercat/ring0/fault" in system.flags, what="drive fault flag")
            assert loop.ticks > 0
        assert "statusword 4616 (0x1208)" in system.flags["ethercat/ring0/fault"]
        status = ring.control.slave(0)
        assert status["drive"]["statusword"] == 4616 and status["drive"]["error_code"] == 0xA000
        assert status["al_state"] != "OP"  # dropped out of OP (AL 0x001A) and never relocks at this frame rate
    finally:
        system.shutdown()


def test_gains_written_over_sdo_read_back(system, ring, robot):
    master = system.master
    with Loop(system, robot.n):
        wait_for(lambda: system.bus_ready, what="SDO gate open")

        sized = SizedSdo(master)

        def write(position: int) -> tuple[int, int]:
            sized.write(position, BUS_GAIN_GATE, 1)
            sized.write(position, POS_LOOP_GAIN, 400 + position)
            sized.write(position, VEL_LOOP_GAIN, 20 + position)
            return sized.read(position, POS_LOOP_GAIN), sized.read(position, VEL_LOOP_GAIN)

        with ThreadPoolExecutor(max_workers=10) as pool:
            read_back = list(pool.map(write, range(10)))
    assert read_back == [(400 + p, 20 + p) for p in range(10)]
    assert [(s["drive"]["pos_reg"], s["drive"]["vel_reg"]) for s in ring.control.status()] == read_back
    assert "ethercat/wkc" not in system.flags


def test_a_lost_slave_raises_flags_while_the_loop_keeps_running(system, ring, robot):
    with Loop(system, robot.n) as loop:
        wait_for(lambda: loop.ticks > 3, what="ticks")
        ring.control.lose_slave(9)
        wait_for(lambda: {"ethercat/ring9/lost", "ethercat/wkc"} <= set(system.flags), what="lost and WKC flags")
        assert system.flags["ethercat/ring9/lost"].startswith("right_wrist_yaw (ring 9): slave lost")
        ticks = loop.ticks
        j = robot.index("left_shoulder_pitch")
        loop.command.position[j] = 0.05
        loop.command.stiffness[j] = 20.0
        wait_for(lambda: abs(loop.state.position[j] - 0.05) < 0.04, what="ring 0 still commanded and read")
        wait_for(lambda: loop.ticks > ticks + 5, what="loop still running")


def test_a_restored_slave_is_recovered_to_op_and_its_drive_held_disabled_until_the_operators_reset(
        system, ring, robot):
    ring.control.set_options(dc_lock_cycles=20)  # a recovering slave relocks at the 50 Hz control rate
    with Loop(system, robot.n):
        ring.control.lose_slave(9)
        wait_for(lambda: "ethercat/ring9/lost" in system.flags, what="lost flag")
        ring.control.restore_slave(9)
        wait_for(lambda: set(system.flags) == {"ethercat/ring9/disabled"}, timeout_s=10.0,
                 what="back in OP, its drive held disabled")
        assert ring.control.slave(9)["drive"]["state"] != "OPERATION_ENABLED"
        system.reset_faults()
        wait_for(lambda: not system.flags, what="every flag cleared after the reset")
        wait_for(lambda: ring.control.slave(9)["drive"]["statusword"] == 5687, what="drive enabled again")
    assert system.master.recoveries >= 1
    assert system.master.left_op[9] >= 1


def test_a_slave_back_from_a_power_cycle_runs_on_the_ring_s_time_again(system, ring, robot):
    # a power cycle clears the slave's DC offset and restarts its clock: SYNC0 on that clock never locks
    ring.control.set_options(dc_lock_cycles=20)
    with Loop(system, robot.n):
        ring.control.lose_slave(9)
        wait_for(lambda: "ethercat/ring9/lost" in system.flags, what="lost flag")
        ring.control.restore_slave(9)
        wait_for(lambda: system.master.slave_ok.all(), timeout_s=10.0, what="ring 9 back in OP")
        differences = [ring.control.slave(k)["dc"]["time_difference_ns"] for k in range(1, 10)]
    assert all(abs(d) <= 10_000 for d in differences), differences
    assert not system.master.recovery_problems


def test_a_reference_clock_back_from_a_power_cycle_is_set_to_the_ring_s_time_again(system, ring, robot):
    # the first slave's clock is the ring's time: back from a power cycle it would restart the ring's time from 0,
    # and every other slave's SYNC0 would be out of step with the frames
    ring.control.set_options(dc_lock_cycles=20)

    def all_in_op() -> bool:
        return (all(s["al_state"] == "OP" for s in ring.control.status()) and system.master.slave_ok.all()
                and "ethercat/wkc" not in system.flags)

    with Loop(system, robot.n):
        ring.control.lose_slave(0)  # the line ends at the master: no slave answers
        wait_for(lambda: "ethercat/wkc" in system.flags, what="working-counter flag")
        assert system.flags["ethercat/wkc"].startswith("no EtherCAT drive answered")
        assert "the power of ring 0 (left_shoulder_pitch)" in system.flags["ethercat/wkc"]
        wait_for(lambda: ring.control.slave(9)["al_state"] == "SAFE-OP", what="the others' watchdogs ran out")
        ring.control.restore_slave(0)
        try:
            wait_for(all_in_op, timeout_s=20.0, what="the whole ring back in OP")
        except AssertionError as exc:
            raise AssertionError(f"{exc}; flags: {system.flags}; problems: {system.master.recovery_problems}; "
                                 f"states: {[s['al_state'] for s in ring.control.status()]}") from None
        differences = [ring.control.slave(k)["dc"]["time_difference_ns"] for k in range(1, 10)]
    assert all(abs(d) <= 10_000 for d in differences), differences
    assert not system.master.recovery_problems


def test_the_cycle_goes_on_while_a_returning_slave_takes_its_time_to_change_state(system, ring, robot):
    # SOEM's reconfiguration waits for each state change in one call that holds Python's lock, so the loop sent
    # nothing until the drive was done: with a drive that takes a second, every other drive's watchdog ran out
    ring.control.set_options(dc_lock_cycles=20, state_change_s=1.0)
    with Loop(system, robot.n):
        ring.control.lose_slave(9)
        wait_for(lambda: "ethercat/ring9/lost" in system.flags, what="lost flag")
        ring.control.restore_slave(9)
        try:
            wait_for(lambda: set(system.flags) == {"ethercat/ring9/disabled"}, timeout_s=20.0,
                     what="back in OP, its drive held disabled")
        except AssertionError as exc:
            raise AssertionError(f"{exc}; flags: {system.flags}") from None
    frames = ring.control.slave(9)["al_change_frames"]
    assert len(frames) >= 2, frames  # PRE-OP and SAFE-OP, each a second late
    assert all(count > 0 for count in frames), f"process-data frames while each state change was pending: {frames}"
    assert not any(ring.control.slave(k)["drive"]["state"] == "FAULT" for k in range(9))


def test_the_start_up_watch_sees_only_its_own_nic_even_while_it_is_being_opened(ring):
    """Other masters send on other NICs beside a scan (the suite's parallel tests; a second Prime on its own ring):
    a frame another NIC sends while the watch's socket is not yet bound to its NIC is not one of SOEM's."""
    with frame_elsewhere_at_each_bind(build_frame(0xD7, [brd(0x0130, 2)])):  # a frame of Prime's indices
        watch = SocketWatch(ring.master_interface)
    try:
        wire = SocketWire(ring.master_interface, 0x40, 0xFF)
        try:
            wire.send(build_frame(0xC6, [brd(0x0130, 2)]))
            assert wire.receive(5.0) is not None
        finally:
            wire.close()
        assert watch.indices() == [0xC6]
    finally:
        watch.close()


def test_the_start_up_watch_counts_frames_sent_from_this_host_and_not_replies(ring):
    """A reply that comes back late to a frame of a master that has ended (a command run just before) carries that
    master's index: the watch of SOEM's scan must not take it for a frame of SOEM's."""
    wire = SocketWire(ring.master_interface, 0x40, 0xFF)
    watch = None
    try:
        ring.control.delay_frames(0.3)  # the next frame is answered 0.3 s late
        wire.send(build_frame(0xC5, [brd(0x0130, 2)]))  # sent before the watch is opened: an earlier master's
        watch = SocketWatch(ring.master_interface)
        reply = wire.receive(5.0)
        assert reply is not None and frame_index(reply) == 0xC5  # its late reply came while the watch looked
        assert watch.indices() == []
        wire.send(build_frame(0xC6, [brd(0x0130, 2)]))
        assert wire.receive(5.0) is not None
        assert watch.indices() == [0xC6]  # a frame sent while it looks, once (its reply is not counted again)
    finally:
        wire.close()
        if watch is not None:
            watch.close()
