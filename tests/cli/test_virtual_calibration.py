"""A run on a virtual robot (the virtual Prime, MuJoCo) never replaces a physical robot's calibration by default:
trying the simulation on the robot's own computer must not reset the offsets its next bring-up reads."""

from __future__ import annotations

import hashlib

import pytest

from humanoid_prime.cli import main
from humanoid_prime.config.calibration import (
    VIRTUAL_MARK,
    Calibration,
    JointCalibration,
    load_calibration,
    save_calibration,
    virtual_may_replace,
)
from humanoid_prime.config.hardware import load_hardware


@pytest.fixture
def folder(tmp_path, monkeypatch):
    config = tmp_path / "prime"
    config.mkdir()
    monkeypatch.setenv("PRIME_CONFIG_DIR", str(config))
    monkeypatch.delenv("PRIME_ROBOT", raising=False)
    assert main(["config", "init"]) == 0
    return config


def measured(hardware, joint="left_elbow_pitch", offset=0.1234) -> Calibration:
    return Calibration({j: JointCalibration(1, offset if j == joint else 0.0) for j in hardware.all_joints})


def test_what_a_virtual_run_may_replace(tmp_path):
    hardware = load_hardware(None)
    path = tmp_path / "cal.yaml"
    assert virtual_may_replace(path, hardware)  # nothing there
    save_calibration(path, Calibration({j: JointCalibration() for j in hardware.all_joints}), hardware)
    assert virtual_may_replace(path, hardware)  # no measurement in it
    save_calibration(path, measured(hardware), hardware)
    assert not virtual_may_replace(path, hardware)  # a physical robot's offsets
    save_calibration(path, measured(hardware), hardware, comment=VIRTUAL_MARK)
    assert virtual_may_replace(path, hardware)  # a virtual run's


@pytest.mark.parametrize("run", [["--sim", "--auto", "left_wrist_yaw"],
                                 ["--emulate", "--scripted", "left_wrist_yaw", "--joints", "left_wrist_yaw"]])
def test_a_virtual_run_refuses_to_replace_the_robots_offsets(folder, run, capsys):
    target = folder / "prime_calibration.yaml"
    hardware = load_hardware(None)
    save_calibration(target, measured(hardware), hardware)
    before = hashlib.sha256(target.read_bytes()).hexdigest()
    assert main(["calibrate", *run]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "physical robot" in err[0] and "--output" in err[0], err
    assert hashlib.sha256(target.read_bytes()).hexdigest() == before


def test_a_flip_keeps_the_virtual_mark(folder):
    target = folder / "prime_calibration.yaml"
    hardware = load_hardware(None)
    save_calibration(target, measured(hardware), hardware, comment=VIRTUAL_MARK)
    assert main(["calibration", "flip", "left_elbow_pitch"]) == 0
    assert VIRTUAL_MARK in target.read_text()
    assert load_calibration(hardware, target).joints["left_elbow_pitch"].direction == -1
