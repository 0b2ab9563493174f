"""Mode requests from outside the loop: followed to their outcome (active, fell back, refused, gains applied),
and on the robot an identity calibration keeps the modes that move joints off (on the doubles, in-process)."""

from __future__ import annotations

import pytest

from humanoid_prime.cli import main
from humanoid_prime.config.calibration import JointCalibration, identity_calibration
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.run import run_loop
from humanoid_prime.runtime.session import MOVING_MODES
from humanoid_prime.runtime.switching import mode_switcher


def ticking(session):
    """Run ``session``'s loop in a thread until the test ends; returns its stop event."""
    import threading

    stop = threading.Event()
    thread = threading.Thread(target=run_loop, args=(session, stop), daemon=True)
    thread.start()

    def end():
        stop.set()
        thread.join(timeout=10)

    return stop, end


def calibrated(robot):
    cal = identity_calibration(robot.hardware)
    return cal.with_joint("left_elbow_pitch", JointCalibration(1, 0.01))


@pytest.mark.parametrize("mode", MOVING_MODES)
def test_on_the_robot_an_identity_calibration_refuses_a_moving_mode_before_any_bus(doubled, mode):
    with pytest.raises(PrimeError, match=f"{mode.value} refused: the calibration .* identity template"):
        doubled.open(uncalibrated=False, mode=mode)
    assert doubled.master is None  # nothing was opened


def test_on_the_robot_an_identity_calibration_refuses_standby_asked_for_while_running(doubled, tmp_path):
    session = doubled.open(uncalibrated=False, control_socket=tmp_path / "sock")
    _, end = ticking(session)
    try:
        assert main(["switch", "STANDBY", "--socket", str(tmp_path / "sock")]) == 1
        assert main(["switch", "DAMPING", "--socket", str(tmp_path / "sock")]) == 0  # holds, moves nothing
    finally:
        end()
    assert "refused" in session.manager.flags.flags and "identity template" in session.manager.flags.flags["refused"]
    assert Mode.STANDBY.value not in session.manager.modes_visited


def test_a_calibrated_robot_enters_standby(doubled, robot):
    session = doubled.open(uncalibrated=False, calibration=calibrated(robot))
    assert session.plan.refused is None
    session.manager.request_mode(Mode.STANDBY)  # no refusal


def test_the_emulated_robot_is_never_refused(doubled):
    assert doubled.open(uncalibrated=False, emulated=True).plan.refused is None


def test_switch_waits_until_the_mode_is_active_with_the_erob_gains_applied(doubled, tmp_path, capsys):
    session = doubled.open(control_socket=tmp_path / "sock")
    assert session.impedance.wait_armed(10.0)
    _, end = ticking(session)
    try:
        assert main(["switch", "STANDBY", "--socket", str(tmp_path / "sock"), "--timeout", "30"]) == 0
    finally:
        end()
    out = capsys.readouterr().out
    assert out.startswith("STANDBY active; gains applied on ") and " ms" in out
    assert session.impedance.reports[-1].mode == "STANDBY" and session.impedance.reports[-1].ok


def test_a_mode_that_falls_back_is_reported_as_such(doubled, tmp_path, capsys, monkeypatch):
    session = doubled.open(control_socket=tmp_path / "sock")
    standby = session.manager.controllers["standby_controller"]

    def broken(*args):
        raise RuntimeError("the standby pose could not be planned")

    monkeypatch.setattr(standby, "update", broken)
    _, end = ticking(session)
    try:
        assert main(["switch", "STANDBY", "--socket", str(tmp_path / "sock")]) == 1
    finally:
        end()
    err = capsys.readouterr().err
    assert err.startswith("prime switch: STANDBY not active (fell back): fell back to DAMPING")
    assert "the standby pose could not be planned" in err


def test_switch_no_wait_only_asks(doubled, tmp_path, capsys):
    session = doubled.open(control_socket=tmp_path / "sock")
    _, end = ticking(session)
    try:
        assert main(["switch", "DAMPING", "--no-wait", "--socket", str(tmp_path / "sock")]) == 0
    finally:
        end()
    assert capsys.readouterr().out == "requested DAMPING\n"


def test_a_gain_write_that_fails_makes_the_switch_fail(doubled):
    session = doubled.open()
    assert session.impedance.wait_armed(10.0)
    master = doubled.master
    original = master.sdo_write

    def refuse_ring3(position, index, sub_index, data):
        if position == 3 and index != 0x2383:
            raise PrimeError("ring 3: SDO abort 0x06010002 (attempt to write a read only object)")
        return original(position, index, sub_index, data)

    master.sdo_write = refuse_ring3
    _, end = ticking(session)
    try:
        answer = mode_switcher(session.manager, session.impedance)(Mode.STANDBY, 30.0)
    finally:
        end()
    assert answer["outcome"] == "gains_failed" and "left_elbow_pitch" in answer["reason"]
    assert list(answer["gains"]["failed"]) == ["left_elbow_pitch"]
