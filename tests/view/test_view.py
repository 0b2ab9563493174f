"""The page works in a real browser: it connects, shows the 14 joints and the mode, a mode button switches the
running simulation, nothing leaves 127.0.0.1, and the robot is drawn."""

from __future__ import annotations

import json
import re
import subprocess

from doubles.process import popen, stop
from humanoid_prime.config.robot import load_robot

from .conftest import PRIME, answering, drawn, start

JOINTS = load_robot(use_sim=True).names


def test_the_page_of_a_running_simulation_shows_it_and_switches_its_mode(browser, tmp_path):
    assert len(JOINTS) == 14
    summary = tmp_path / "sim.json"
    sim, url = start("sim", "--web", "--port", "0", "--mode", "DAMPING", "--duration", "300", "--summary", str(summary),
                     "--socket", str(tmp_path / "control.sock"))
    try:
        page = browser.page
        page.goto(url)
        page.get_by_text("mode DAMPING").wait_for(timeout=60_000)
        for joint in JOINTS:
            page.get_by_text(joint, exact=True).first.wait_for(timeout=30_000)
        page.get_by_text(re.compile(r"^elapsed \d+\.\d s  loop \d+\.\d Hz of 200 Hz$")).wait_for(timeout=30_000)
        page.get_by_role("cell", name="left_elbow_pitch").wait_for(timeout=30_000)  # its row in the drive table
        page.get_by_role("button", name="STANDBY").click()
        page.get_by_text("mode STANDBY").wait_for(timeout=60_000)  # the simulation's own /control_mode
        page.wait_for_timeout(1500)  # STANDBY lifts the arms; let a few frames draw
        shot = page.locator("canvas").first.screenshot()
        (tmp_path / "view.png").write_bytes(shot)
    finally:
        stop(sim)
    assert browser.hosts() == {"127.0.0.1"}, browser.urls
    picture = drawn(shot)
    assert picture["colours"] > 500 and picture["erob_pixels"] > 2000, picture
    visited = json.loads(summary.read_text())["modes_visited"]
    assert visited[-1] == "STANDBY"


def test_prime_view_attaches_to_a_running_simulation_over_its_control_socket(browser, tmp_path):
    socket = str(tmp_path / "control.sock")
    sim = popen([*PRIME, "sim", "--mode", "DAMPING", "--duration", "300", "--socket", socket],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    view = None
    try:
        answering(socket, sim)
        view, url = start("view", "--port", "0", "--socket", socket)
        page = browser.page
        page.goto(url)
        page.get_by_text("mode DAMPING").wait_for(timeout=60_000)
        page.get_by_role("button", name="ZERO_TORQUE").click()
        page.get_by_text("mode ZERO_TORQUE").wait_for(timeout=60_000)
    finally:
        for process in (view, sim):
            if process is not None:
                stop(process)
    assert browser.hosts() == {"127.0.0.1"}


def test_with_no_running_instance_prime_view_says_so_at_once(tmp_path):
    done = subprocess.run([*PRIME, "view", "--port", "0", "--socket", str(tmp_path / "nobody.sock")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert done.stderr.startswith(f"prime view: no running prime instance listens on {tmp_path / 'nobody.sock'}")


def test_a_run_that_goes_away_shows_as_not_connected_and_a_request_shows_its_refusal(browser, tmp_path):
    socket = str(tmp_path / "control.sock")
    sim = popen([*PRIME, "sim", "--mode", "DAMPING", "--duration", "300", "--socket", socket],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    view = None
    try:
        answering(socket, sim)
        view, url = start("view", "--port", "0", "--socket", socket)
        page = browser.page
        page.goto(url)
        page.get_by_text("mode DAMPING").wait_for(timeout=60_000)
        stop(sim)
        page.get_by_text("not connected").first.wait_for(timeout=60_000)
        page.get_by_role("button", name="STANDBY").click()
        page.get_by_text("STANDBY refused: no running prime instance listens on").wait_for(timeout=30_000)
    finally:
        for process in (view, sim):
            if process is not None:
                stop(process)


def test_a_recording_replays_into_the_view_once_a_browser_opens_it_and_pauses_and_seeks(browser, tmp_path):
    recording = tmp_path / "run.mcap"
    subprocess.run([*PRIME, "sim", "--fast", "--record", str(recording)], check=True, capture_output=True,
                   timeout=300)
    # --loop: the replay is still playing whenever this browser gets to the button, however slow the machine.
    replay, url = start("replay", str(recording), "--port", "0", "--speed", "2", "--loop")
    try:
        page = browser.page
        page.goto(url)  # the replay waits for this browser: it sees the start, ZERO_TORQUE
        page.get_by_text("mode ZERO_TORQUE").wait_for(timeout=60_000)
        page.get_by_text("mode STANDBY").wait_for(timeout=60_000)  # the demonstration's third mode, played
        page.get_by_role("button", name="pause").click()
        page.get_by_text("(paused)").wait_for(timeout=30_000)
        paused = page.get_by_text(" s of ").first.inner_text()
        page.wait_for_timeout(1000)
        assert page.get_by_text(" s of ").first.inner_text() == paused  # time stands still while paused
        page.get_by_role("button", name="play").click()
        page.get_by_text("(paused)").wait_for(state="detached", timeout=30_000)
    finally:
        stop(replay)


def test_the_drive_table_shows_each_joints_torque_and_its_drives_statusword_and_al_state(sim_robot):
    from humanoid_prime.control.hardware import DriveStatus
    from humanoid_prime.view.page import drive_table

    effort = [0.0] * 14
    effort[3], effort[6] = 2.3, float("nan")  # left_wrist_yaw not measured (the other bus of a one-bus run)
    table = drive_table(sim_robot, effort, {"left_elbow_pitch": DriveStatus("left_elbow_pitch", 0x1208, 0x8500, 0x14)})
    assert ("<tr><td>left_elbow_pitch</td><td align=right>+2.30</td><td>0x1208</td><td>fault</td>"
            "<td>SAFE-OP + ERROR</td></tr>") in table
    assert "<tr><td>left_wrist_roll</td><td align=right>+0.00</td><td>—</td><td>—</td><td>—</td></tr>" in table
    assert "<td>left_wrist_yaw</td><td align=right>—</td>" in table
    assert table.count("<tr>") == 15
    assert "<td>left_shoulder_pitch</td><td align=right>—</td>" in drive_table(sim_robot, None, {})


def test_a_calibration_page_shows_each_joints_swept_range(browser, sim_robot):
    """What `prime calibrate --web` serves on the robot: the swept range beside each joint's position."""
    from humanoid_prime.view.page import PrimeView

    view = PrimeView(sim_robot, port=0, sweeps=True)
    try:
        view.update(position=[0.0] * 14, mode=None,
                    sweeps=[(j.lower + 0.1, j.upper - 0.1) if j.family == "sito" else (1.0, -1.0)
                            for j in sim_robot.joints])
        page = browser.page
        page.goto(view.url)
        page.get_by_text("calibration: swept range within limits (rad)").wait_for(timeout=60_000)
        for joint in JOINTS:
            page.get_by_text(f"{joint} swept", exact=True).wait_for(timeout=30_000)
    finally:
        view.close()
    assert browser.hosts() == {"127.0.0.1"}
