"""The eRob impedance manager writes each mode's loop gains as DESIGN §2/§3 require."""

import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from doubles.mailboxes import FACTORY_WINDOW, DriveMailboxes
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.control.flags import Level
from humanoid_prime.control.topics import CONTROL_MODE, JOINT_STATES, ControlMode, JointState, TopicBus
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD
from humanoid_prime.drivers.erob.gains import gains_to_registers
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.impedance import CONFIRM_PAUSE_S, CONFIRM_READS, ImpedanceManager


@pytest.fixture
def gains(robot):
    return load_controllers(robot.names).mode_gains()


def make(robot, gains, drives, **kw):
    return ImpedanceManager(robot, drives, gains, **kw)


def publish_joint_states(topics, robot):
    z = np.zeros(robot.n)
    topics.publish(JOINT_STATES, JointState(0.0, robot.names, z, z, z))


def on_topics(robot, gains):
    """Drives, a topic bus whose joint states have flowed, and a manager on both (not started)."""
    drives, topics = DriveMailboxes(), TopicBus()
    publish_joint_states(topics, robot)
    return drives, topics, make(robot, gains, drives)


def expected(mode_gains, mode):
    kp, kd = mode_gains[mode]
    return gains_to_registers(kp, kd, kt=0.132e-3, gear=50.0, efficiency=1.0)


def test_nothing_touches_the_bus_before_op_and_joint_states(robot, gains):
    drives = DriveMailboxes()
    topics = TopicBus()
    ready = threading.Event()
    mgr = make(robot, gains, drives)
    asked = threading.Semaphore(0)

    def bus_ready() -> bool:
        asked.release()
        return ready.is_set()

    starter = threading.Thread(target=mgr.start, args=(topics, bus_ready), kwargs={"timeout": 30.0})
    starter.start()
    publish_joint_states(topics, robot)  # joint states alone are not enough
    for _ in range(5):  # the manager has looked at the bus five times, found it not ready, and waited on
        assert asked.acquire(timeout=30.0)
    assert drives.log == [] and drives.most_in_flight == 0 and not mgr.armed
    ready.set()
    starter.join(timeout=5.0)
    assert mgr.armed
    mgr.close()


@pytest.mark.parametrize("joint_states", [True, False])
def test_a_bus_that_never_gets_ready_is_refused_with_what_it_lacks(robot, gains, joint_states):
    drives = DriveMailboxes()
    topics = TopicBus()
    ticks = iter(range(0, 100, 3))  # an injected clock: 3 s per look, past the 5 s deadline at the third
    mgr = make(robot, gains, drives, clock=lambda: float(next(ticks)))
    if joint_states:
        publish_joint_states(topics, robot)
    lacks = "ring 3 SAFE-OP + ERROR (AL status 0x001A synchronization error)"
    with pytest.raises(PrimeError) as refused:
        mgr.start(topics, lambda: False, timeout=5.0, why_not_ready=lambda: lacks)
    words = lacks if joint_states else "no joint states were published"
    assert str(refused.value) == ("eRob impedance manager: the ring did not reach OP with joint states flowing "
                                  f"within 5 s ({words}); no gains were written")
    assert drives.log == [] and not mgr.armed
    mgr.close()


def test_the_window_then_the_gate_go_before_any_gain_on_every_slave(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives)
    mgr.arm()
    mgr.apply(Mode.STANDBY)
    for position in range(10):
        writes = [entry[2] for entry in drives.log if entry[1] == position]
        assert writes[:2] == ["window", "gate"] and {"pos_reg", "vel_reg"} <= set(writes[2:])
    mgr.close()


@pytest.mark.parametrize("joint, window_rad", [("left_shoulder_pitch", 3.0), ("left_wrist_yaw", 1.0)])
def test_the_following_window_admits_twice_the_sag_at_the_effort_limit_of_the_stiffest_mode(robot, gains, joint,
                                                                                              window_rad):
    """kp 20 (STANDBY, LOCOMOTION, REMOTE): a shoulder (30 Nm) sags up to 1.5 rad, wrist yaw (10 Nm) 0.5 rad."""
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives)
    mgr.arm()
    position = robot.hardware.erob_slaves[joint]
    assert drives.values[position]["window"] == round(window_rad * COUNTS_PER_RAD)
    mgr.close()
    assert drives.values[position]["window"] == FACTORY_WINDOW


def test_a_drive_with_a_wider_window_keeps_it(robot, gains):
    drives = DriveMailboxes()
    drives.values[0]["window"] = 10 * round(3.0 * COUNTS_PER_RAD)
    mgr = make(robot, gains, drives)
    mgr.arm()
    assert drives.values[0]["window"] == 10 * round(3.0 * COUNTS_PER_RAD)
    mgr.close()


@pytest.mark.parametrize("gain_bytes", [2, 4])
def test_gains_are_written_with_the_size_the_drive_holds_them_in(robot, gains, gain_bytes):
    drives = DriveMailboxes(gain_bytes=gain_bytes)  # a drive that aborts any other length
    mgr = make(robot, gains, drives)
    mgr.arm()
    report = mgr.apply(Mode.STANDBY)
    assert report.ok and drives.registers(3)[:2] == (515, 19)
    mgr.close()


def test_a_gate_armed_whose_registers_cannot_be_read_back_is_a_warning_not_an_unarmed_gate(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives)
    real_read = drives.sdo_read

    def registers_unreadable(position, index, sub):
        if position == 2 and index == 0x2381:
            raise PrimeError("ring 2: no reply")
        return real_read(position, index, sub)

    drives.sdo_read = registers_unreadable
    mgr.arm()
    assert drives.values[2]["gate"] == 1
    assert "gate armed, gain registers not read back" in mgr.flags["erob/impedance/ring2"]
    assert mgr.levels["erob/impedance/ring2"] is Level.WARN
    drives.sdo_read = real_read
    assert mgr.apply(Mode.STANDBY).ok
    mgr.close()


def test_standby_and_damping_registers_match_design(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives)
    mgr.arm()
    mgr.apply(Mode.STANDBY)
    standby = expected(gains, Mode.STANDBY)
    assert (standby.vel_reg, standby.pos_reg, standby.integral) == (19, 515, 0)
    assert all(drives.registers(p) == (515, 19, 0) for p in range(10))
    mgr.apply(Mode.DAMPING)
    assert all(drives.registers(p) == (0, 56, 0) for p in range(10))
    mgr.close()


def _stiffness(pos_reg, vel_reg):
    return pos_reg * vel_reg, vel_reg  # kp ∝ pos·vel, kd ∝ vel


@pytest.mark.parametrize("sequence", [
    [Mode.DAMPING, Mode.STANDBY, Mode.DAMPING],
    [Mode.STANDBY, Mode.ZERO_TORQUE, Mode.STANDBY],
    [Mode.ZERO_TORQUE, Mode.DAMPING, Mode.REMOTE, Mode.DAMPING],
])
def test_no_intermediate_pair_is_stiffer_than_both_modes(robot, gains, sequence):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives)
    mgr.arm()
    for mode in sequence:
        before = {p: drives.registers(p) for p in range(10)}
        start = len(drives.log)
        mgr.apply(mode)
        for p in range(10):
            old = before[p]
            new = drives.registers(p)
            pos, vel = old[0], old[1]
            for _, position, name, value in drives.log[start:]:
                if position != p:
                    continue
                pos = value if name == "pos_reg" else pos
                vel = value if name == "vel_reg" else vel
                kp, kd = _stiffness(pos, vel)
                assert kp <= max(_stiffness(old[0], old[1])[0], _stiffness(new[0], new[1])[0])
                assert kd <= max(old[1], new[1])
    mgr.close()


def test_only_changed_registers_are_written(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives)
    mgr.arm()
    mgr.apply(Mode.STANDBY)
    start = len(drives.log)
    report = mgr.apply(Mode.LOCOMOTION)  # same eRob gains as STANDBY
    assert drives.log[start:] == []
    assert all(s.writes == () for s in report.slaves)
    mgr.close()


def test_switch_report_has_wall_time_and_skew(robot, gains):
    mgr = make(robot, gains, DriveMailboxes(latency_s=0.002))
    mgr.arm()
    report = mgr.apply(Mode.STANDBY)
    assert report.ok and report.wall_seconds > 0
    assert 0 <= report.skew_seconds <= report.wall_seconds
    assert set(report.as_dict()) >= {"mode", "wall_seconds", "skew_seconds", "retries"}
    mgr.close()


def test_parallel_writes_overlap_on_the_slaves_and_sequential_ones_never_do(robot, gains):
    # parallel: every transfer waits in the drive until a second is in flight beside it (however long the machine
    # takes to start the workers); sequential: nothing could ever be beside it
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives, parallel=True)
    mgr.arm()
    drives.meet = threading.Event()
    report = mgr.apply(Mode.STANDBY)
    drives.meet = None
    mgr.close()
    assert report.ok and drives.most_in_flight >= 2
    drives = DriveMailboxes(latency_s=0.002)
    mgr = make(robot, gains, drives, parallel=False)
    mgr.arm()
    mgr.apply(Mode.STANDBY)
    mgr.close()
    assert drives.most_in_flight == 1


def switch_entries(drives, since):
    """The writes of one switch from the drives' log: (log index, position, register) per write."""
    return [(i, position, name) for i, (_t, position, name, _v) in enumerate(drives.log[since:])]


def test_every_slave_makes_its_last_write_only_after_every_slave_made_its_others(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives, rendezvous_s=60.0)
    mgr.arm()
    drives.slow[3] = 0.05  # one slow mailbox: the other nine would be done before its first write
    since = len(drives.log)
    report = mgr.apply(Mode.STANDBY)
    entries = switch_entries(drives, since)
    last = {position: i for i, position, _name in entries}
    earlier = [i for i, position, _name in entries if i != last[position]]
    assert len(last) == 10 and len(earlier) == 20  # integral, vel_reg, then pos_reg on every slave
    assert min(last.values()) > max(earlier)
    assert report.ok and report.together
    mgr.close()


def test_a_slave_that_fails_before_its_last_write_does_not_hold_the_others(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives, retries=0, rendezvous_s=60.0)
    mgr.arm()
    drives.fail_next[7] = 100
    report = mgr.apply(Mode.STANDBY)
    assert report.together  # it met the others on its way out, so nobody waited for the 60 s
    assert [s.position for s in report.slaves if s.error] == [7]
    assert all(drives.registers(p) == (515, 19, 0) for p in range(10) if p != 7)
    drives.fail_next[7] = 0
    mgr.close()


def test_a_slave_that_hangs_lets_the_others_make_their_last_write_after_the_rendezvous_time(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives, rendezvous_s=0.05)
    mgr.arm()
    release = drives.hold(3)
    since = len(drives.log)
    reports = []
    switch = threading.Thread(target=lambda: reports.append(mgr.apply(Mode.STANDBY)))
    switch.start()
    others = set(range(10)) - {3}
    deadline = time.monotonic() + 60.0
    while {p for _i, p, name in switch_entries(drives, since) if name == "pos_reg"} != others:
        assert time.monotonic() < deadline, "the others never made their last write"
        time.sleep(0.005)
    release.set()
    switch.join()
    (report,) = reports
    assert report.ok and not report.together
    assert report.as_dict()["together"] is False
    mgr.close()


def test_failed_write_is_retried_within_bound(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives, retries=3)
    mgr.arm()
    drives.fail_next[4] = 2
    report = mgr.apply(Mode.STANDBY)
    assert report.ok and report.retries == 2
    assert drives.registers(4) == (515, 19, 0)
    assert mgr.flags == {}
    mgr.close()


def test_exhausted_retries_raise_a_flag_naming_the_slave(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives, retries=1)
    mgr.arm()
    drives.fail_next[7] = 100
    report = mgr.apply(Mode.STANDBY)
    assert not report.ok
    (text,) = mgr.flags.values()
    assert "right_shoulder_yaw (ring 7)" in text and "STANDBY" in text
    assert mgr.flags_version > 0
    assert all(drives.registers(p) == (515, 19, 0) for p in range(10) if p != 7)
    drives.fail_next[7] = 0
    assert mgr.apply(Mode.STANDBY).ok
    assert mgr.flags == {}
    mgr.close()


def test_close_resets_the_gate_on_every_slave(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives)
    mgr.arm()
    mgr.apply(Mode.DAMPING)
    assert mgr.close() == []
    assert all(drives.values[p]["gate"] == 0 for p in range(10))


def test_close_reports_unreachable_slaves(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives)
    mgr.arm()
    drives.dead.add(2)
    failures = mgr.close()
    assert len(failures) == 1 and "ring 2" in failures[0]
    assert all(drives.values[p]["gate"] == 0 for p in range(10) if p != 2)


def test_mode_changes_on_the_topic_are_applied(robot, gains):
    drives, topics, mgr = on_topics(robot, gains)
    topics.publish(CONTROL_MODE, ControlMode("ZERO_TORQUE", "zero_torque_controller"))
    mgr.start(topics, lambda: True)
    assert mgr.wait_idle(5.0)  # armed, then the latched mode applied
    topics.publish(CONTROL_MODE, ControlMode("STANDBY", "standby_controller"))
    assert mgr.wait_idle(5.0)
    assert [r.mode for r in mgr.reports] == ["ZERO_TORQUE", "STANDBY"]
    assert all(drives.registers(p) == (515, 19, 0) for p in range(10))
    mgr.close()


def test_the_worker_arms_the_gate_before_any_mode_and_a_mode_asked_meanwhile_is_applied_after(robot, gains):
    drives, topics, mgr = on_topics(robot, gains)
    topics.publish(CONTROL_MODE, ControlMode("ZERO_TORQUE", "zero_torque_controller"))
    release = drives.hold(0)  # the first slave's arming waits on this: the loop would be ticking meanwhile
    mgr.start(topics, lambda: True)  # returns with the arming under way
    topics.publish(CONTROL_MODE, ControlMode("STANDBY", "standby_controller"))
    assert not mgr.wait_armed(0.05) and mgr.reports == []
    release.set()
    assert mgr.wait_armed(5.0) and mgr.wait_idle(5.0)
    for position in range(10):
        writes = [entry[2] for entry in drives.log if entry[1] == position]
        assert writes[:2] == ["window", "gate"]
    assert [r.mode for r in mgr.reports] == ["STANDBY"]  # the newest request, once armed
    assert all(drives.registers(p) == (515, 19, 0) for p in range(10))
    mgr.close()


def test_a_close_during_the_arming_leaves_every_gate_reset(robot, gains):
    drives, topics, mgr = on_topics(robot, gains)
    release = drives.hold(9)
    mgr.start(topics, lambda: True)
    closing = threading.Thread(target=lambda: failures.extend(mgr.close()))
    failures: list[str] = []
    closing.start()
    release.set()
    closing.join(10.0)
    assert failures == [] and not closing.is_alive()
    assert all(drives.values[p]["gate"] == 0 for p in range(10))


def test_per_joint_kt_scales_only_vel_reg(robot, gains, tmp_path):
    import yaml

    from humanoid_prime.config.hardware import load_hardware
    from humanoid_prime.config.robot import build_robot

    data = yaml.safe_load(robot.hardware.path.read_text())
    data["joints"]["erob_kt"] = {"left_elbow_pitch": 0.134e-3}
    path = tmp_path / "hw.yaml"
    path.write_text(yaml.safe_dump(data))
    robot80 = build_robot(load_hardware(path), robot.description)
    mgr = make(robot80, gains, DriveMailboxes())
    regs = mgr.targets[Mode.DAMPING]
    assert regs[3].vel_reg == round(6 / 0.1063 * 0.132 / 0.134)
    assert regs[3].pos_reg == regs[0].pos_reg
    mgr.close()


def test_a_gate_that_failed_to_arm_is_armed_before_gains_and_stays_flagged_until_it_is(robot, gains):
    drives = DriveMailboxes()
    drives.dead.add(4)
    mgr = make(robot, gains, drives, retries=0)
    mgr.arm()
    assert "erob/impedance/ring4" in mgr.flags
    report = mgr.apply(Mode.ZERO_TORQUE)  # gain writes would be ignored with the gate at 0
    assert not report.ok and "erob/impedance/ring4" in mgr.flags
    drives.dead.discard(4)
    assert mgr.apply(Mode.STANDBY).ok
    assert drives.values[4]["gate"] == 1 and drives.registers(4) == (515, 19, 0)
    assert mgr.flags == {}
    mgr.close()


def test_a_bug_in_the_arming_is_flagged_and_no_gain_is_written(robot, gains, monkeypatch):
    drives, topics, mgr = on_topics(robot, gains)
    topics.publish(CONTROL_MODE, ControlMode("STANDBY", "standby_controller"))

    def broken() -> None:
        raise RuntimeError("boom")

    monkeypatch.setattr(mgr, "arm", broken)
    mgr.start(topics, lambda: True)
    assert mgr.wait_armed(5.0) and mgr.wait_idle(5.0)
    assert mgr.flags["erob/impedance/arming"] == "gate not armed: RuntimeError: boom"
    assert mgr.flags["erob/impedance/worker"].startswith("mode STANDBY not applied: PrimeError")
    assert drives.log == []
    mgr.close()


class Dropped:
    """The EtherCAT side's held drives, as the impedance manager sees them."""

    def __init__(self, positions):
        self.on_restore_needed = None
        self.waiting = list(positions)
        self.released: list[int] = []
        self.restored = threading.Event()

    def awaiting_restore(self):
        return [(p, 0) for p in self.waiting if p not in self.released]

    def restore_pending(self):
        return [p for p in self.waiting if p not in self.released]

    def settings_restored(self, position, left_op):
        self.released.append(position)
        self.restored.set()


def flagged(mgr, key, timeout=30.0) -> bool:
    deadline = time.monotonic() + timeout
    while key not in mgr.flags:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def test_a_slave_back_from_a_power_loss_gets_window_gate_and_the_current_modes_gains_again(robot, gains):
    drives, topics, mgr = on_topics(robot, gains)
    dropped = Dropped([])
    topics.publish(CONTROL_MODE, ControlMode("STANDBY", "standby_controller"))
    mgr.start(topics, lambda: True, dropped=dropped)
    assert mgr.wait_idle(5.0) and mgr.wait_checked(5.0) and mgr.flags == {}
    chosen = dict(drives.values[5])
    drives.values[5] = {"gate": 0, "pos_reg": 300, "vel_reg": 94, "integral": 5, "window": FACTORY_WINDOW}
    drives.fail_next[5] = 100  # the restore fails: the drive stays held, and it is flagged
    dropped.waiting = [5]
    dropped.on_restore_needed()  # as the EtherCAT side says once the slave is back in OP
    assert flagged(mgr, "erob/impedance/ring5")
    assert dropped.released == [] and dropped.restore_pending() == [5]  # still pending: the worker looks again
    assert "ring 5" in mgr.flags["erob/impedance/ring5"] and "stays held disabled" in mgr.flags["erob/impedance/ring5"]
    drives.fail_next[5] = 0
    dropped.on_restore_needed()
    assert dropped.restored.wait(30.0)
    assert dropped.released == [5] and drives.values[5] == chosen
    assert "erob/impedance/ring5" not in mgr.flags
    names = [name for _, position, name, _ in mgr.sdo_log if position == 5][-5:]
    assert names[:2] == ["following_window", "gate"]  # the window, then the gate, before any gain
    mgr.close()


class Ring:
    """The AL states a master would read after a switch."""

    def __init__(self, states: dict[int, int] | None = None) -> None:
        self.states = states or {}

    def read_states(self):
        from humanoid_prime.drivers.ethercat.ring import SlaveInfo

        return [SlaveInfo(p, "eRob", 0, 0, 0, self.states.get(p, 0x08)) for p in range(10)]


def test_a_switch_is_ok_only_when_every_slave_is_in_op_after_it(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives, states=Ring({4: 0x11}))  # ring 4 dropped to INIT with its error flag
    mgr.arm()
    report = mgr.apply(Mode.STANDBY)
    assert not report.ok
    assert report.as_dict()["failed"] == {
        "left_wrist_yaw": "STANDBY switch: the slave is in INIT + ERROR after it, not OP"}
    assert "INIT + ERROR" in mgr.flags["erob/impedance/ring4"]
    mgr.close()


class UnansweredReads(Ring):
    """A ring whose first ``unanswered`` reads of the AL states come back unanswered (0 for every slave)."""

    def __init__(self, unanswered: int) -> None:
        super().__init__()
        self.unanswered = unanswered
        self.reads = 0

    def read_states(self):
        self.reads += 1
        answered = super().read_states()
        return [replace(s, al_state=0) for s in answered] if self.reads <= self.unanswered else answered


def test_an_unanswered_read_of_the_al_states_is_made_again_before_the_switch_is_judged(robot, gains):
    drives = DriveMailboxes()
    ring = UnansweredReads(2)  # a busy host lost two reads' frames
    mgr = make(robot, gains, drives, states=ring)
    mgr.arm()
    report = mgr.apply(Mode.STANDBY)
    assert report.ok and ring.reads == 3
    assert not any(key.startswith("erob/impedance/ring") for key in mgr.flags)
    mgr.close()


def test_a_ring_that_answers_no_read_of_its_states_leaves_the_switch_not_confirmed_and_says_so(robot, gains):
    drives = DriveMailboxes()
    ring = UnansweredReads(1000)
    mgr = make(robot, gains, drives, states=ring)
    mgr.arm()
    report = mgr.apply(Mode.STANDBY)
    assert not report.ok and ring.reads == CONFIRM_READS
    assert report.as_dict()["failed"]["left_wrist_yaw"] == (
        f"STANDBY switch: its AL state after it is unknown (it answered none of {CONFIRM_READS} reads of its AL "
        f"state over {CONFIRM_READS * CONFIRM_PAUSE_S:g} s)")
    mgr.close()


def test_the_gains_are_read_back_without_holding_the_switch_and_a_drive_holding_others_is_flagged(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives, states=Ring())
    mgr.arm()
    drives.values[6]["gate"] = 0  # ring 6 lost its gate: it takes the gain writes and ignores them
    drives.reads_held = threading.Event()
    report = mgr.apply(Mode.STANDBY)
    assert report.ok and not report.checked.is_set()  # done before anything was read back
    drives.reads_held.set()
    assert mgr.wait_checked(10.0)
    assert not report.ok
    (problem,) = report.as_dict()["failed"].values()
    assert problem == ("STANDBY switch: gains read back as {'pos_reg': 300, 'vel_reg': 94, 'integral': 5}, not "
                       "{'pos_reg': 515, 'vel_reg': 19, 'integral': 0}")
    assert "erob/impedance/ring6" in mgr.flags
    mgr.close()


def test_the_summary_lists_per_slave_what_was_written_and_read_back_the_retries_and_the_wall_time(robot, gains):
    drives = DriveMailboxes()
    mgr = make(robot, gains, drives, states=Ring())
    mgr.arm()
    drives.fail_next[2] = 1
    report = mgr.apply(Mode.STANDBY)
    mgr.wait_checked(10.0)
    summary = report.as_dict()
    assert summary["ok"] and summary["read_back"] == "done" and summary["failed"] == {}
    row = next(s for s in summary["slaves"] if s["position"] == 2)
    assert row["written"] == {"integral": 0, "vel_reg": 19, "pos_reg": 515}
    assert row["read_back"] == {"pos_reg": 515, "vel_reg": 19, "integral": 0}
    assert row["retries"] == 1 and row["al_state"] == "OP" and 0 < row["seconds"] <= summary["wall_seconds"]
    mgr.close()
