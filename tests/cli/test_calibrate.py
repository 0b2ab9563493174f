"""`prime calibrate` end to end on the virtual Prime with injected wiring directions and factory offsets."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from doubles.process import popen
from humanoid_prime.calibration.math import flip_direction
from humanoid_prime.config.calibration import Calibration, JointCalibration, load_calibration, save_calibration
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import package_root
from humanoid_prime.runtime.socket import SocketSdoClient, request
from humanoid_prime.virtual.netns import netns_unavailable_reason

REASON = netns_unavailable_reason()
pytestmark = [pytest.mark.netns, pytest.mark.skipif(REASON is not None, reason=f"emulated calibration: {REASON}")]

PRIME = [sys.executable, "-m", "humanoid_prime"]
FLIPPED = ("left_shoulder_roll", "right_wrist_pitch", "right_wrist_yaw")


def prime(*args: str, timeout: float = 240.0, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([*PRIME, *args], capture_output=True, text=True, timeout=timeout, env=env)


def package_files() -> dict[str, str]:
    """sha256 of every file of the installed package (its code and bundled templates)."""
    root = package_root()
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and "__pycache__" not in p.parts}


@pytest.fixture(scope="module")
def truth(robot, tmp_path_factory) -> tuple[Calibration, Path]:
    """Random factory offsets on every joint, three joints wired backwards."""
    rng = random.Random(20261121)
    cal = Calibration({j: JointCalibration(-1 if j in FLIPPED else 1, round(rng.uniform(-0.9, 0.9), 5))
                       for j in robot.names})
    path = tmp_path_factory.mktemp("truth") / "truth.yaml"
    save_calibration(path, cal, robot.hardware)
    return cal, path


@pytest.fixture(scope="module")
def home(tmp_path_factory) -> dict:
    """A new user's environment: a fresh HOME, no configuration anywhere, the package's files as installed."""
    home = tmp_path_factory.mktemp("home")
    env = {k: v for k, v in os.environ.items() if k not in ("XDG_CONFIG_HOME", "PRIME_CONFIG_DIR", "PRIME_ROBOT")}
    env.update(HOME=str(home), PRIME_CONTROL_SOCKET=str(home / "control.sock"))
    return {"env": env, "home": home, "package": package_files()}


@pytest.fixture(scope="module")
def calibrated(robot, truth, home, tmp_path_factory) -> tuple[dict, Path, Path]:
    """The operator's first steps with nothing but defaults: `prime config init`, then the default procedure
    with the template's (all +1) directions: one command sweeps the ten eRob on EtherCAT alone, then the four
    wrists on CAN alone with the eRob result as their prior, into the robot's own calibration file. Returns the
    report, a copy of the file as the run wrote it, and the plot."""
    tmp = tmp_path_factory.mktemp("calibrate")
    assert prime("config", "init", env=home["env"]).returncode == 0
    plot = tmp / "sweeps.png"
    proc = prime("calibrate", "--emulate", "--truth", str(truth[1]), "--scripted", "--plot", str(plot),
                 "--record", str(tmp / "run.mcap"), "--json", env=home["env"])
    # Three joints are wired backwards: the run says so, exits 1, and names the flip to run next.
    assert proc.returncode == 1, proc.stderr
    assert f"Next: prime calibration flip {FLIPPED[0]} (then {FLIPPED[1]}, {FLIPPED[2]})" in proc.stderr
    result = json.loads(proc.stdout)
    robot_file = home["home"] / ".config" / "prime" / "prime_calibration.yaml"
    assert result["output"] == str(robot_file) and sorted(result["not_calibrated"]) == sorted(FLIPPED)
    copy = tmp / "as_written.yaml"
    copy.write_bytes(robot_file.read_bytes())
    joints = result["joints"]
    return {"joints": {j: r for j, r in joints.items() if r["status"] != "carried"}}, copy, plot


@pytest.fixture(scope="module")
def operator_loop(robot, truth, home, calibrated, tmp_path_factory) -> dict:
    """The rest of the operator's loop, as the calibration run told it: check, flip each flagged joint, then
    bring the robot up in STANDBY; every command finds the robot's file by itself."""
    env, tmp = home["env"], tmp_path_factory.mktemp("loop")
    check = prime("calibration", "check", env=env)
    flips = [prime("calibration", "flip", joint, env=env) for joint in FLIPPED]
    summary = tmp / "summary.json"
    bringup = prime("bringup", "--emulate", "--truth", str(truth[1]), "--mode", "STANDBY", "--duration", "6",
                    "--no-live", "--summary", str(summary), env=env)
    return {"check": check, "flips": flips, "bringup": bringup,
            "summary": json.loads(summary.read_text()) if summary.exists() else None,
            "robot_file": home["home"] / ".config" / "prime" / "prime_calibration.yaml"}


def test_the_operator_loop_brings_up_the_robot_on_the_calibration_just_written_and_flipped(robot, truth,
                                                                                          operator_loop):
    loop = operator_loop
    assert loop["check"].returncode == 0 and str(loop["robot_file"]) in loop["check"].stdout
    for flip in loop["flips"]:
        assert flip.returncode == 0 and f"wrote {loop['robot_file']}" in flip.stdout, flip.stderr
    assert loop["bringup"].returncode == 0, loop["bringup"].stderr
    used = loop["summary"]["config"]["calibration"]
    assert used["path"] == str(loop["robot_file"])
    assert used["sha256"] == hashlib.sha256(loop["robot_file"].read_bytes()).hexdigest()
    measured, true = loop["summary"]["end"]["position"], loop["summary"]["emulator"]["joints"]
    for joint in robot.names:
        assert measured[joint] == pytest.approx(true[joint], abs=1e-3), joint


def test_no_command_of_the_loop_wrote_inside_the_installed_package(home, operator_loop):
    assert package_files() == home["package"]


def test_every_correctly_wired_offset_is_recovered_within_1_mrad(robot, truth, calibrated):
    report, output, _ = calibrated
    written = load_calibration(robot.hardware, output)
    for joint, true in truth[0].joints.items():
        if joint in FLIPPED:
            continue
        assert report["joints"][joint]["status"] == "calibrated", report["joints"][joint]
        assert written.joints[joint].homing_offset == pytest.approx(true.homing_offset, abs=1e-3), joint


def test_joints_wired_backwards_are_flagged_and_a_flip_recovers_them(robot, truth, calibrated):
    report, output, _ = calibrated
    flagged = {j for j, r in report["joints"].items() if r["status"] == "probable_flip"}
    assert flagged == set(FLIPPED)
    written = load_calibration(robot.hardware, output)
    for joint in FLIPPED:
        spec = robot.joints[robot.index(joint)]
        fixed = flip_direction(written.joints[joint], spec.lower, spec.upper)
        assert fixed.direction == truth[0].joints[joint].direction
        assert fixed.homing_offset == pytest.approx(truth[0].joints[joint].homing_offset, abs=1e-3), joint


def test_the_plot_is_written(calibrated):
    _, _, plot = calibrated
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_both_phases_are_in_one_recording(robot, calibrated):
    """--record: the EtherCAT phase and the CAN phase, one after the other, in one readable file."""
    from rosbags.highlevel import AnyReader

    _, output, _ = calibrated
    with AnyReader([output.parent / "run.mcap"]) as reader:
        states = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                  if c.topic == "/prime/joint_states"]
    assert len(states) > 100 and all(tuple(s.name) == robot.names for s in states)
    for joint in ("left_elbow_pitch", "left_wrist_pitch"):  # one of each phase (NaN while the other bus runs)
        swept = [s.position[robot.index(joint)] for s in states]
        assert max(v for v in swept if v == v) - min(v for v in swept if v == v) > 0.5, joint


def test_after_folding_every_joint_at_a_stop_reads_its_limit(robot, truth, calibrated, tmp_path):
    _, output, _ = calibrated
    fixed = tmp_path / "fixed.yaml"
    fixed.write_bytes(output.read_bytes())
    for joint in FLIPPED:
        assert prime("calibration", "flip", joint, "--calibration", str(fixed)).returncode == 0
    proc = prime("calibrate", "--emulate", "--verify", "--truth", str(truth[1]), "--calibration", str(fixed),
                 "--socket", str(tmp_path / "control.sock"), "--json")
    result = json.loads(proc.stdout)
    bad = [r for r in result["rows"] if not r["ok"]]
    assert proc.returncode == 0 and not bad, bad
    assert len(result["rows"]) == 28
    assert max(abs(r["error"]) for r in result["rows"]) <= 0.002


def test_an_unswept_joint_keeps_its_prior_and_is_listed(robot, truth, tmp_path):
    prior = tmp_path / "prior.yaml"
    cal = Calibration({j: JointCalibration(1, 0.0) for j in robot.names}).with_joint(
        "right_shoulder_yaw", JointCalibration(1, 0.4321))
    save_calibration(prior, cal, robot.hardware)
    output = tmp_path / "out.yaml"
    proc = prime("calibrate", "--emulate", "--backends", "ec", "--truth", str(truth[1]), "--prior", str(prior),
                 "--scripted", "right_shoulder_pitch,right_elbow_pitch", "--output", str(output),
                 "--socket", str(tmp_path / "control.sock"), "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert report["joints"]["right_shoulder_yaw"]["status"] in ("skipped", "carried")
    written = load_calibration(robot.hardware, output)
    assert written.joints["right_shoulder_yaw"].homing_offset == pytest.approx(0.4321)
    assert set(written.joints) == set(robot.names)  # a one-bus run still writes all 14 joints
    assert written.joints["right_elbow_pitch"].homing_offset == pytest.approx(
        truth[0].joints["right_elbow_pitch"].homing_offset, abs=1e-3)


def _start(tmp_path: Path, output: Path, *extra: str) -> tuple[subprocess.Popen, Path]:
    socket = tmp_path / "control.sock"
    proc = popen([*PRIME, "calibrate", "--emulate", "--output", str(output), "--socket", str(socket),
                             "--no-live", *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while True:
        with contextlib.suppress(PrimeError):
            if request(socket, {"op": "ping"}, timeout=0.5)["ready"]:
                return proc, socket
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(proc.stderr.read())
        time.sleep(0.1)


@pytest.mark.parametrize("signals", [1, 2])
def test_ctrl_c_leaves_the_previous_file_or_a_complete_new_one(robot, tmp_path, signals):
    output = tmp_path / "prime_calibration.yaml"
    previous = Calibration({j: JointCalibration(1, 0.1234) for j in robot.names})
    save_calibration(output, previous, robot.hardware)
    before = output.read_text()
    proc, _ = _start(tmp_path, output, "--scripted")
    time.sleep(2.0)  # somewhere in the middle of the scripted sweeps
    for _ in range(signals):
        proc.send_signal(signal.SIGINT)
        time.sleep(0.05)
    proc.wait(timeout=60)
    text = output.read_text()
    assert text == before or set(yaml.safe_load(text)["joints"]) == set(robot.names)
    load_calibration(robot.hardware, output)  # whichever it is, it is complete and valid
    assert not list(tmp_path.glob(".prime_calibration.yaml.*.tmp"))


@pytest.mark.parametrize("how", ["seconds", "sigterm"])
def test_prime_limp_leaves_the_registers_as_it_found_them(tmp_path, how):
    proc, socket = _start(tmp_path, tmp_path / "out.yaml")
    try:
        sdo = SocketSdoClient(socket)
        objects = [(0x2383, 0), (0x2382, 1), (0x2381, 1), (0x2381, 2)]
        before = [sdo.sdo_read(3, index, sub) for index, sub in objects]
        if how == "seconds":
            limp = subprocess.run([*PRIME, "limp", "3", "--seconds", "0.5", "--socket", str(socket)],
                                  capture_output=True, text=True, timeout=60)
            assert limp.returncode == 0, limp.stderr
        else:
            limp = popen([*PRIME, "limp", "3", "--socket", str(socket)], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            deadline = time.monotonic() + 30
            while int.from_bytes(sdo.sdo_read(3, 0x2382, 1)[:4], "little") != 0:
                assert time.monotonic() < deadline, "the joint never went limp"
                time.sleep(0.05)
            limp.send_signal(signal.SIGTERM)
            limp.communicate(timeout=30)
            assert limp.returncode == 130
        after = [sdo.sdo_read(3, index, sub) for index, sub in objects]
        assert after == before
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=60)


GAINS = [(0x2383, 0), (0x2382, 1), (0x2381, 1), (0x2381, 2)]  # gate, pos_reg, vel_reg, integral


def test_a_prime_limp_killed_outright_is_restored_by_the_next_one_which_says_so(tmp_path):
    """SIGKILL runs no exit path: the drive stays limp (gate 1, pos_reg 0). The next `prime limp` through the same
    run finds the record the killed one left, puts the drive back as that one found it, and says so; only then
    does it take its own snapshot (which would otherwise be of the limp drive, and restore it limp)."""
    proc, socket = _start(tmp_path, tmp_path / "out.yaml")
    try:
        sdo = SocketSdoClient(socket)

        def gains() -> list[int]:
            return [int.from_bytes(sdo.sdo_read(3, index, sub), "little") for index, sub in GAINS]

        before = gains()
        limp = popen([*PRIME, "limp", "3", "--socket", str(socket)], stdin=subprocess.PIPE,
                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 30
        while gains()[1] != 0:
            assert time.monotonic() < deadline, "the joint never went limp"
            time.sleep(0.05)
        limp.kill()
        limp.communicate(timeout=30)
        assert gains()[:2] == [1, 0]  # left limp
        again = subprocess.run([*PRIME, "limp", "3", "--seconds", "0", "--socket", str(socket)],
                               capture_output=True, text=True, timeout=60)
        assert again.returncode == 0, again.stderr
        assert gains() == before
        told = [line for line in again.stderr.splitlines() if line.strip()]
        assert len(told) == 1 and told[0].startswith("ring 3 (left_elbow_pitch) was left limp by `prime limp 3` "
                                                     f"(pid {limp.pid}, "), told
        assert told[0].endswith("which ended without restoring it: restored its gains as found, "
                                + " ".join(f"{name}={value}" for name, value in
                                           zip(("gate", "pos_reg", "vel_reg", "integral"), before, strict=True)))
        third = subprocess.run([*PRIME, "limp", "3", "--seconds", "0", "--socket", str(socket)],
                               capture_output=True, text=True, timeout=60)
        assert third.returncode == 0 and third.stderr == "", third.stderr  # restored once, the record gone
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=60)


def test_on_a_busy_machine_the_run_calibrates_every_joint_asked_for_or_names_what_it_missed(robot, truth, tmp_path):
    from doubles.load import busy_cores

    joints = ("left_shoulder_pitch", "left_elbow_pitch", "right_shoulder_yaw")  # wired as the template says
    output = tmp_path / "cal.yaml"
    with busy_cores(2):
        proc = prime("calibrate", "--emulate", "--backends", "ec", "--truth", str(truth[1]), "--scripted",
                     ",".join(joints), "--output", str(output), "--socket", str(tmp_path / "control.sock"), "--json")
    result = json.loads(proc.stdout)
    missed = [j for j in joints if result["joints"][j]["status"] != "calibrated"]
    assert result["not_calibrated"] == missed
    if proc.returncode == 0:  # never 0 with a joint missed or a device faulted
        assert not missed and result["ok"] and not [f for f in result["faults"] if f["level"] == "ERROR"]
    else:
        assert "NOT complete" in proc.stderr and all(j in proc.stderr for j in missed)
