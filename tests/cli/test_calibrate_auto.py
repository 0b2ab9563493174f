"""``prime calibrate --auto`` as a user runs it: in MuJoCo alone (``--sim``) on the model's own stops, and end to end
through the real drivers against the virtual Prime (``--emulate``), then ``--apply``; and every option it refuses,
with one line."""

from __future__ import annotations

import contextlib
import json
import random
import subprocess
import sys

import pytest

from humanoid_prime.calibration.auto import contact_cap
from humanoid_prime.config.calibration import Calibration, JointCalibration, load_calibration, save_calibration
from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.files import bundled
from humanoid_prime.virtual.netns import netns_unavailable_reason
from humanoid_prime.virtual.ring.drive import REALISED_EFFICIENCY

PRIME = [sys.executable, "-m", "humanoid_prime"]


def prime(*args: str, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run([*PRIME, *args], capture_output=True, text=True, timeout=timeout, stdin=subprocess.DEVNULL)


@pytest.mark.parametrize(("args", "says"), [
    (["--apply"], "--apply: only with --auto"),
    (["--sim"], "--sim: only with --auto"),
    (["--auto", "--verify"], "--auto does not go with --verify"),
    (["--auto", "--emulate", "--scripted"], "--auto does not go with --scripted"),
    (["--auto", "--apply"], "--apply writes the measured efficiencies into the robot's hardware file"),
    (["--auto", "--sim", "--emulate"], "--sim and --emulate are two different virtual robots"),
    (["--auto", "nose", "--sim"], "--auto: unknown joint 'nose'"),
    (["--auto", "--speed", "0.3", "--sim"], "--speed: must be at most 0.2"),
    (["--auto"], "--auto on the robot waits for the operator at each joint: run it at a terminal"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_refused_with_one_line_and_nothing_written(tmp_path, capsys, args, says):
    """In this process (stdin is no terminal here, as in a pipe); nothing reaches a bus."""
    from humanoid_prime.cli import main

    output = tmp_path / "prime_calibration.yaml"
    output.write_bytes(bundled("prime_calibration.yaml").read_bytes())
    before = output.read_bytes()
    with pytest.raises(SystemExit) if "--speed" in args else contextlib.nullcontext() as exited:
        code = main(["calibrate", "--output", str(output), "--socket", str(tmp_path / "s.sock"), *args])
    code = exited.value.code if "--speed" in args else code
    assert code != 0
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and says in lines[0], lines
    assert output.read_bytes() == before


def test_in_mujoco_alone_every_joint_is_found_where_the_model_has_it(robot, tmp_path):
    """The model's own stops: every offset within a milliradian of zero, every direction +1, exit 0. One arm (both
    families; the lockstep tests run all fourteen in MuJoCo): a whole arm is about half the robot's robot minutes."""
    output, plot = tmp_path / "prime_calibration.yaml", tmp_path / "auto.png"
    arm = [j for j in robot.names if j.startswith("right_")]
    proc = prime("calibrate", "--sim", "--auto", *arm, "--output", str(output), "--plot", str(plot), "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads(proc.stdout)
    assert report["complete"] and report["aborted"] is None
    written = load_calibration(robot.hardware, output)
    for joint in arm:
        assert report["joints"][joint]["status"] == "done", report["joints"][joint]
        assert written.joints[joint].direction == 1
        assert abs(written.joints[joint].homing_offset) <= 1e-3, joint
        assert report["joints"][joint]["peak_contact_nm"] <= contact_cap(robot, joint)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_in_mujoco_alone_a_direction_asked_for_says_the_simulated_operator_answered(tmp_path):
    # wrist_yaw's limits are symmetric and gravity cannot tell: the direction question is asked, and nobody is there
    proc = prime("calibrate", "--sim", "--auto", "right_wrist_yaw", "--output", str(tmp_path / "cal.yaml"), "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    joint = json.loads(proc.stdout)["joints"]["right_wrist_yaw"]
    assert joint["direction_source"] == "the simulated operator's answer (it saw the joint's true motion; no one " \
                                       "was asked)"
    assert joint["message"].startswith(f"direction from {joint['direction_source']}")


@pytest.mark.netns
@pytest.mark.skipif(netns_unavailable_reason() is not None, reason=str(netns_unavailable_reason()))
def test_end_to_end_on_the_virtual_prime_through_the_real_drivers_then_apply(robot, tmp_path):
    """An eRob joint (SDO gains, the gate, the window, 0x6072, over SOEM) and a Sito wrist (MIT over CAN), on a
    robot whose other joints are calibrated: offsets within a milliradian, directions right, the file complete;
    the elbow's realised stiffness within 5 % of the emulated drive's; --apply writes it into the hardware file."""
    rng = random.Random(3636)
    joints = ("left_wrist_roll", "left_elbow_pitch")
    truth = Calibration({j: JointCalibration(rng.choice((1, -1)), round(rng.uniform(-0.5, 0.5), 5))
                         for j in robot.names}).with_joint("left_elbow_pitch", JointCalibration(-1, 0.31))
    truth_file, output = tmp_path / "truth.yaml", tmp_path / "prime_calibration.yaml"
    save_calibration(truth_file, truth, robot.hardware)
    prior = Calibration({j: JointCalibration() if j in joints else c for j, c in truth.joints.items()})
    save_calibration(output, prior, robot.hardware)  # the robot's file: every joint but these two calibrated
    hardware = tmp_path / "prime_hardware.yaml"
    hardware.write_text(bundled("prime_hardware.yaml").read_text())
    proc = prime("calibrate", "--emulate", "--truth", str(truth_file), "--auto", *joints, "--output", str(output),
                 "--hardware", str(hardware), "--apply", "--socket", str(tmp_path / "control.sock"), "--json")
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    report = json.loads(proc.stdout)
    written = load_calibration(robot.hardware, output)
    for joint in robot.names:
        if joint in joints:
            assert report["joints"][joint]["status"] == "done", report["joints"][joint]
            assert written.joints[joint].direction == truth.joints[joint].direction, joint
            assert written.joints[joint].homing_offset == pytest.approx(truth.joints[joint].homing_offset, abs=1e-3)
        else:
            assert written.joints[joint] == prior.joints[joint]  # not asked for: kept
    elbow = report["joints"]["left_elbow_pitch"]
    assert elbow["flipped"] and elbow["direction_source"].startswith("limits")
    assert elbow["stiffness"]["torque_efficiency"] == pytest.approx(REALISED_EFFICIENCY, rel=0.05)
    assert "then 1500 again" in elbow["drive_torque_limit"]  # the drive's own limit set, and put back
    assert report["applied"] == {"left_elbow_pitch": pytest.approx(REALISED_EFFICIENCY, rel=0.05)}
    assert load_hardware(hardware).erob_torque_efficiency["left_elbow_pitch"] == report["applied"]["left_elbow_pitch"]
