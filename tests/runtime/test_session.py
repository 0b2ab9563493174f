"""A whole session on the doubles: the staged bring-up, the impedance manager following the mode, the run
policy, the control socket glue and the report."""

from __future__ import annotations

import struct
import sys
import threading

import numpy as np
import pytest

from humanoid_prime.drivers.erob.objects import BUS_GAIN_GATE, FOLLOWING_ERROR_WINDOW, POS_LOOP_GAIN, VEL_LOOP_GAIN
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.run import close_impedance_while_ticking, run_loop
from humanoid_prime.runtime.session import claim_control_socket, plan_session
from humanoid_prime.runtime.socket import request


def gate(master, position: int) -> int:
    return int.from_bytes(master.objects[(position, *BUS_GAIN_GATE)], "little")


def test_a_full_session_comes_up_in_the_documented_stages(doubled):
    session = doubled.open()
    assert [name for name, _ in session.stages] == [
        "configuration", "hardware configure", "joint_state_broadcaster", "zero_torque_controller",
        "damping_controller", "standby_controller", "locomotion_controller", "remote_policy_controller",
        "hardware activate", "controllers activated", "first tick", "impedance manager started"]
    assert session.manager.active_mode is Mode.ZERO_TORQUE
    assert np.all(np.isfinite(session.manager.resources.state.position))  # all 14 joints measured


def test_from_bring_up_on_the_interpreter_switches_threads_within_a_tenth_of_the_period(doubled, monkeypatch):
    # the keeper thread sends the frames between bring-up and the loop while the main thread builds controllers
    from doubles.master import FakeMaster

    before = sys.getswitchinterval()
    seen = []
    request_op = FakeMaster._request_op
    monkeypatch.setattr(FakeMaster, "_request_op", lambda self: (seen.append(sys.getswitchinterval()),
                                                                   request_op(self)))
    doubled.open(update_rate=1000.0)
    assert seen == [pytest.approx(1e-4)] and sys.getswitchinterval() == pytest.approx(1e-4)
    doubled.stack.close()
    assert sys.getswitchinterval() == before


def test_once_the_session_is_up_its_impedance_worker_arms_the_gate_on_every_slave(doubled):
    session = doubled.open()
    assert session.impedance.wait_armed(5.0)
    assert [gate(doubled.master, p) for p in range(10)] == [1] * 10


def test_a_mode_switch_writes_that_modes_gains_to_every_slave(doubled):
    session = doubled.open()
    session.manager.request_mode(Mode.STANDBY)
    session.manager.tick()
    assert session.impedance.wait_idle(10.0)
    pos_reg, vel_reg = (struct.unpack("<H", doubled.master.objects[(3, *a)])[0] for a in (POS_LOOP_GAIN,
                                                                                          VEL_LOOP_GAIN))
    assert (pos_reg, vel_reg) == (515, 19)  # STANDBY kp 20, kd 2 (DESIGN §2)
    assert session.summary()["mode_switches"][-1]["mode"] == "STANDBY"


def test_the_run_ends_after_its_sequence_and_resets_every_gate_while_still_ticking(doubled):
    session = doubled.open(sequence=(Mode.DAMPING, Mode.STANDBY), dwell=0.05)
    run_loop(session, threading.Event())
    assert session.manager.modes_visited[-2:] == ["DAMPING", "STANDBY"]
    assert [gate(doubled.master, p) for p in range(10)] == [0] * 10
    assert session.gate_reset_failures == []


def test_a_single_bus_session_runs_only_the_broadcaster_and_arms_nothing(doubled):
    session = doubled.open(backends="ec")
    assert session.manager.broadcaster_only and session.impedance is None and session.sito is None
    assert not [entry for entry in doubled.master.sdo_log if entry[0] == "write"]


def test_the_control_socket_switches_modes_of_a_full_session(doubled, tmp_path):
    session = doubled.open(control_socket=tmp_path / "control.sock")
    assert request(tmp_path / "control.sock", {"op": "mode", "mode": "damping"})["mode"] == "DAMPING"
    session.manager.tick()
    assert session.manager.active_mode is Mode.DAMPING


def test_in_a_calibration_session_the_socket_marks_a_joint_limp_and_resets_its_gate_at_the_end(doubled, tmp_path):
    path = tmp_path / "control.sock"
    session = doubled.open(backends="ec", control_socket=path)
    assert request(path, {"op": "limp", "position": 4, "limp": True})["joint"] == "left_wrist_yaw"
    command = session.manager.resources.command
    assert np.isnan(command.position[6])  # nothing writes the command between ticks
    session.manager.tick()  # the passive controller writes it, through the gate
    assert np.isfinite(command.position[6]) and command.stiffness[6] == 0.0  # a finite target: it follows the joint
    assert np.isnan(command.position[0])  # the others: no command
    session.plan.control.detach()  # the run ends
    assert gate(doubled.master, 4) == 0
    assert any(f.key == "limp/ring4" and "still limp when the run ended" in f.text for f in session.faults)


def test_closing_the_impedance_while_ticking_resets_the_gates(doubled):
    session = doubled.open()
    close_impedance_while_ticking(session)
    assert [gate(doubled.master, p) for p in range(10)] == [0] * 10


def test_an_unknown_backend_is_refused_before_anything_opens(doubled):
    with pytest.raises(PrimeError, match="backends must be one of all, ec, can"):
        plan_session(doubled.options(backends="both"))


def test_a_sync0_period_that_differs_from_the_loop_is_refused_before_anything_opens(doubled):
    with pytest.raises(PrimeError, match="differs from the loop period"):
        plan_session(doubled.options(sync0_period_s=0.001))


def run_ticks(session, count: int) -> None:
    for _ in range(count):
        session.manager.tick()


def test_a_drive_fault_during_the_run_makes_the_report_a_failure_with_the_fault_and_its_time(doubled):
    session = doubled.open()
    run_ticks(session, 3)
    doubled.master.fault(2, 0x8500)
    run_ticks(session, 3)
    session.capture_end()
    summary = session.summary()
    assert not summary["ok"]
    fault = next(f for f in summary["faults"] if f["key"] == "PrimeEtherCATSide/ethercat/ring2/fault")
    assert fault["level"] == "ERROR" and "0x8500" in fault["text"] and fault["since_s"] > 0
    assert any(line.startswith("PrimeEtherCATSide/ethercat/ring2/fault at ") for line in summary["problems"])


def test_the_end_counts_what_holds_then_not_what_was_reached_earlier(doubled):
    session = doubled.open()
    run_ticks(session, 3)
    doubled.master.states[5] = 0x04  # ring 5 dropped to SAFE-OP
    session.capture_end()
    assert session.end["slaves_op"] == 9 and session.end["slaves"] == 10
    assert "1 of 10 EtherCAT slaves not in OP at the end" in session.problems


def test_a_run_with_warnings_only_is_a_success(doubled):
    session = doubled.open()
    session.manager.request_mode(Mode.REMOTE)  # no remote stream: REMOTE warns that it waits, and damps
    run_ticks(session, 5)
    session.capture_end()
    summary = session.summary()
    assert summary["ok"], summary["problems"]
    assert [f["level"] for f in summary["faults"]] == ["WARN"]
    assert "waiting for the first command" in summary["faults"][0]["text"]


def test_a_flag_that_cleared_stays_in_the_history_with_the_time_it_cleared(doubled):
    session = doubled.open()
    session.manager.request_mode(Mode.REMOTE)
    run_ticks(session, 2)
    session.manager.request_mode(Mode.DAMPING)
    run_ticks(session, 2)
    (record,) = session.faults
    assert record.until_s is not None and record.until_s >= record.since_s


def test_a_second_instance_stops_at_the_socket_before_it_opens_a_bus(doubled, tmp_path):
    path = tmp_path / "control.sock"
    doubled.open(control_socket=path)
    first_master = doubled.master
    with pytest.raises(PrimeError, match="another prime instance already listens"):
        doubled.open(control_socket=path)
    assert doubled.master is first_master  # the second run built no EtherCAT component


def test_until_the_session_is_up_the_socket_answers_not_ready(doubled, tmp_path):
    path = tmp_path / "control.sock"
    plan = plan_session(doubled.options(control_socket=path))
    claim_control_socket(plan, doubled.stack)
    with pytest.raises(PrimeError, match="starting up or shutting down"):
        request(path, {"op": "mode", "mode": "STANDBY"})


def test_the_bringup_loop_runs_at_least_twice_as_fast_as_sync0_up_to_the_erobs_2_khz():
    from humanoid_prime.runtime.session import default_bringup_rate

    assert default_bringup_rate(1000.0, 50.0) == 1000.0
    assert default_bringup_rate(1000.0, 1000.0) == 2000.0
    assert default_bringup_rate(1000.0, 2000.0) == 2000.0
    assert default_bringup_rate(1500.0, 50.0) == 1500.0


def registers(master, position: int) -> tuple[int, int]:
    return tuple(struct.unpack("<H", master.objects[(position, *a)])[0] for a in (POS_LOOP_GAIN, VEL_LOOP_GAIN))


def window(master, position: int) -> int:
    return struct.unpack("<i", master.objects[(position, FOLLOWING_ERROR_WINDOW, 0)])[0]


def test_a_drive_back_from_a_power_loss_gets_its_window_gate_and_gains_again_before_a_reset_enables_it(doubled):
    from doubles.master import OPERATION_ENABLED

    session = doubled.open()
    master, manager = doubled.master, session.manager
    manager.request_mode(Mode.STANDBY)
    run_ticks(session, 5)
    assert session.impedance.wait_idle(10.0)
    assert master.statusword[3] == OPERATION_ENABLED
    chosen = registers(master, 3), window(master, 3)
    doubled.power_cycle(3)
    assert (gate(master, 3), registers(master, 3)) == (0, (300, 94))  # factory, as a drive that lost power
    run_ticks(session, 1)
    assert "reset" in session.ethercat.flags["ethercat/ring3/disabled"]
    deadline = threading.Event()
    for _ in range(2000):  # the worker restores it within its next looks; ticks go on meanwhile
        if session.impedance.restored:
            break
        deadline.wait(0.005)
        run_ticks(session, 1)
    assert [joint for _, joint in session.impedance.restored] == [session.impedance.slaves[3].joint]
    assert (gate(master, 3), (registers(master, 3), window(master, 3))) == (1, chosen)
    run_ticks(session, 5)
    assert master.statusword[3] != OPERATION_ENABLED  # restored, still held until the operator's reset
    manager.request_reset()
    run_ticks(session, 5)
    assert master.statusword[3] == OPERATION_ENABLED
    assert "ethercat/ring3/disabled" not in session.ethercat.flags


def test_the_control_sockets_state_carries_the_loop_rate_torques_and_drive_states_a_view_shows(doubled, tmp_path):
    from humanoid_prime.view.feeds import socket_source

    session = doubled.open(control_socket=tmp_path / "control.sock")
    doubled.master.torque_per_mille[3] = 100  # ring 3, left_elbow_pitch: a tenth of its 23 Nm
    doubled.master.fault(8, 0x8500)  # ring 8, right_elbow_pitch
    run_ticks(session, 3)
    state, _ = socket_source(tmp_path / "control.sock")  # what `prime view --socket` polls
    seen = state()
    assert seen["update_rate_hz"] == session.manager.update_rate and seen["elapsed_s"] > 0
    assert seen["rate_hz"] > 0
    assert seen["effort"][3] == pytest.approx(2.3)
    assert seen["drives"]["right_elbow_pitch"] == {"statusword": 0x1208, "error_code": 0x8500, "al_state": 0x08}
    assert seen["drives"]["left_shoulder_pitch"]["statusword"] == 0x1637
    assert "left_wrist_roll" not in seen["drives"]  # a Sito wrist has no CiA402 drive
