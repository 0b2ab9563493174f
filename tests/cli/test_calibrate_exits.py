"""`prime calibrate` never weakens the calibration it replaces, however the run ends: Ctrl-C, SIGTERM, q,
an exception, with or without anything swept. On the doubles (the eRob ring on the master double), so
every exit path runs in this process."""

from __future__ import annotations

import os
import signal

import pytest

from humanoid_prime.cli import calibrate as calibrate_cli
from humanoid_prime.cli import main
from humanoid_prime.config.calibration import Calibration, JointCalibration, load_calibration, save_calibration
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD
from humanoid_prime.runtime.run import run_loop

ELBOW = "left_elbow_pitch"  # ring 3, limits [-2.356, 0]


@pytest.fixture
def good(robot, tmp_path):
    """A finished calibration with wired-backwards joints and real offsets, as a robot's file would be."""
    cal = Calibration({j: JointCalibration(-1 if i % 3 == 0 else 1, round(0.05 * (i - 7), 3))
                       for i, j in enumerate(robot.names)})
    path = tmp_path / "prime_calibration.yaml"
    save_calibration(path, cal, robot.hardware)
    return path


def calibrate(tmp_path, output, *extra: str) -> int:
    return main(["calibrate", "--backends", "ec", "--output", str(output), "--socket", str(tmp_path / "sock"),
                 "--no-live", *extra])


def ending(monkeypatch, end, sweep_elbow: bool = False, doubled=None) -> None:
    """Replace the run loop of each phase: optionally sweep the elbow stop to stop on the master double,
    then end the way ``end()`` does (a signal, a key, an exception), then run the loop as the CLI would."""

    def loop(session, stop, on_tick=None):
        if sweep_elbow:
            master = doubled.master
            direction = session.plan.calibration.joints[ELBOW].direction
            for q in (-2.356 - 0.1, 0.0 - 0.1):  # identity frame (direction applied): true offset -0.1 * direction
                master.position_counts[3] = round(direction * q * COUNTS_PER_RAD)
                for _ in range(3):
                    session.manager.tick()
        end(stop)
        run_loop(session, stop, on_tick)

    monkeypatch.setattr(calibrate_cli, "run_loop", loop)


def written(robot, path) -> Calibration:
    return load_calibration(robot.hardware, path)


@pytest.mark.parametrize("end", ["ctrl-c", "sigterm", "q"])
def test_an_end_with_nothing_swept_writes_nothing_and_says_so(doubled, robot, good, tmp_path, monkeypatch, capsys,
                                                             end):
    before = good.read_bytes()
    ends = {"ctrl-c": lambda stop: os.kill(os.getpid(), signal.SIGINT),
            "sigterm": lambda stop: os.kill(os.getpid(), signal.SIGTERM),
            "q": lambda stop: stop.set()}
    ending(monkeypatch, ends[end])
    assert calibrate(tmp_path, good) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing was swept" in err[0] and "is as it was" in err[0]
    assert good.read_bytes() == before


@pytest.mark.parametrize("end", ["ctrl-c", "sigterm", "q"])
def test_an_end_after_one_joint_was_swept_changes_that_joint_only(doubled, robot, good, tmp_path, monkeypatch, end):
    prior = written(robot, good)
    ends = {"ctrl-c": lambda stop: os.kill(os.getpid(), signal.SIGINT),
            "sigterm": lambda stop: os.kill(os.getpid(), signal.SIGTERM),
            "q": lambda stop: stop.set()}
    ending(monkeypatch, ends[end], sweep_elbow=True, doubled=doubled)
    assert calibrate(tmp_path, good, "--any-order", "--joints", ELBOW) == 0
    after = written(robot, good)
    for joint in robot.names:
        if joint == ELBOW:
            assert after.joints[joint].direction == prior.joints[joint].direction
            assert after.joints[joint].homing_offset == pytest.approx(-0.1 * prior.joints[joint].direction, abs=1e-4)
        else:
            assert after.joints[joint] == prior.joints[joint], joint


def test_an_exception_in_the_run_leaves_the_file_as_it_was(doubled, robot, good, tmp_path, monkeypatch, capsys):
    before = good.read_bytes()

    def broken(stop):
        raise OSError("EtherCAT interface gone")

    ending(monkeypatch, broken, sweep_elbow=True, doubled=doubled)
    assert calibrate(tmp_path, good) != 0
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line == "prime calibrate: EtherCAT interface gone"
    assert good.read_bytes() == before


def test_the_prior_is_the_file_being_replaced_not_the_bundled_identity(doubled, robot, good, tmp_path, monkeypatch):
    ending(monkeypatch, lambda stop: stop.set(), sweep_elbow=True, doubled=doubled)
    assert calibrate(tmp_path, good, "--any-order", "--joints", ELBOW) == 0
    after = written(robot, good)
    assert [after.joints[j].direction for j in robot.names] == [-1 if i % 3 == 0 else 1 for i in range(14)]


def test_a_new_file_starts_from_the_bundled_calibration(doubled, robot, tmp_path, monkeypatch):
    output = tmp_path / "new" / "prime_calibration.yaml"
    ending(monkeypatch, lambda stop: stop.set(), sweep_elbow=True, doubled=doubled)
    assert calibrate(tmp_path, output, "--any-order", "--joints", ELBOW) == 0
    after = written(robot, output)
    assert after.joints[ELBOW].homing_offset == pytest.approx(-0.1, abs=1e-4)
    assert after.joints["left_shoulder_pitch"] == JointCalibration(1, 0.0)


def test_joints_asked_for_but_not_swept_make_the_run_fail_and_the_file_lists_them(doubled, robot, good, tmp_path,
                                                                                   monkeypatch, capsys):
    ending(monkeypatch, lambda stop: stop.set(), sweep_elbow=True, doubled=doubled)
    assert calibrate(tmp_path, good, "--any-order") == 1  # every eRob joint was asked for; one was swept
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("prime calibrate: NOT complete: 9 of 10 joints not calibrated (")
    assert "Next: prime calibrate --backends ec --joints left_shoulder_pitch," in err[0]
    header = [line for line in good.read_text().splitlines() if line.startswith("#")]
    assert f"# calibrated in this run: {ELBOW}" in header
    assert any(line.startswith("# asked for but not calibrated: left_shoulder_pitch, ") for line in header)
    assert written(robot, good).joints["left_shoulder_pitch"].homing_offset == pytest.approx(-0.35)  # prior kept


def test_a_probable_flip_fails_the_run_and_names_the_flip_to_run(doubled, robot, tmp_path, monkeypatch, capsys):
    output = tmp_path / "prime_calibration.yaml"

    def loop(session, stop, on_tick=None):  # the elbow swept upper stop first although lower was asked for
        for q in (-1.2, 0.0 - 0.1, -2.356 - 0.1):
            doubled.master.position_counts[3] = round(q * COUNTS_PER_RAD)
            for _ in range(3):
                session.manager.tick()
        stop.set()
        run_loop(session, stop, on_tick)

    monkeypatch.setattr(calibrate_cli, "run_loop", loop)
    assert calibrate(tmp_path, output, "--joints", ELBOW) == 1
    err = capsys.readouterr().err
    assert f"Next: prime calibration flip {ELBOW} --calibration {output}" in err
    assert "# PROBABLE DIRECTION FLIP" in output.read_text()
