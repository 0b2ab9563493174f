"""The operator's view and keys: live table, progress lines, and mode keys on a terminal."""

import io
import os
import pty
import termios
import time

import pytest
from rich.console import Console

from humanoid_prime.cli._live import MODE_KEYS, LiveTable, ModeKeys, ProgressLines  # private to cli/: no terminal
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.modes import Mode
from humanoid_prime.sim.demo import Simulation, Step, build_simulation


@pytest.fixture()
def started(sim_robot):
    system, manager = build_simulation(sim_robot, load_controllers(sim_robot.names))
    with manager:
        manager.start()
        yield system, manager


def test_number_keys_1_to_5_select_the_modes_in_ladder_order():
    assert MODE_KEYS == {"1": Mode.ZERO_TORQUE, "2": Mode.DAMPING, "3": Mode.STANDBY, "4": Mode.LOCOMOTION,
                         "5": Mode.REMOTE}


def test_a_mode_key_requests_its_mode_and_q_quits():
    modes, quits = [], []
    keys = ModeKeys(modes.append, lambda: quits.append(True), stream=io.StringIO())
    for key in "3x5q":
        keys.press(key)
    assert modes == [Mode.STANDBY, Mode.REMOTE]
    assert quits == [True]


def test_mode_keys_stay_off_when_input_is_not_a_terminal():
    read, write = os.pipe()
    try:
        with os.fdopen(read, closefd=False) as stream, ModeKeys(print, print, stream=stream) as keys:
            assert not keys.active
    finally:
        os.close(read)
        os.close(write)


@pytest.fixture()
def terminal():
    master, slave = pty.openpty()
    with os.fdopen(slave, "r", closefd=True) as stream:
        yield master, stream
    os.close(master)


def test_mode_keys_read_a_terminal_in_cbreak_mode_and_restore_it(terminal):
    master, stream = terminal
    before = termios.tcgetattr(stream.fileno())
    modes = []
    with ModeKeys(modes.append, lambda: None, stream=stream) as keys:
        assert keys.active
        assert not termios.tcgetattr(stream.fileno())[3] & termios.ICANON
        os.write(master, b"2")
        deadline = time.monotonic() + 2.0
        while not modes and time.monotonic() < deadline:
            time.sleep(0.01)
    assert modes == [Mode.DAMPING]
    assert termios.tcgetattr(stream.fileno()) == before


def test_mode_keys_restore_the_terminal_when_the_run_fails(terminal):
    _, stream = terminal
    before = termios.tcgetattr(stream.fileno())
    with pytest.raises(RuntimeError), ModeKeys(print, print, stream=stream):
        raise RuntimeError("the loop failed")
    assert termios.tcgetattr(stream.fileno()) == before


def test_progress_lines_print_once_per_mode(started):
    system, manager = started
    out = io.StringIO()
    progress = ProgressLines(manager, stream=out, clock=lambda: system.sim_time)
    sim = Simulation(system, manager, schedule=(Step(0.1, Mode.DAMPING), Step(0.2, Mode.STANDBY)),
                     realtime=False)
    sim.run(0.3, on_tick=progress.poll)
    lines = out.getvalue().splitlines()
    assert [line.split()[2] for line in lines] == ["ZERO_TORQUE", "DAMPING", "STANDBY"]


def test_live_table_shows_the_mode_every_joint_and_the_loop_timing(started, sim_robot):
    system, manager = started
    Simulation(system, manager, realtime=False).run(0.05)
    console = Console(file=io.StringIO(), width=140)
    console.print(LiveTable(manager, console=console, status=lambda: "sim 0.05 s", keys=True).render())
    text = console.file.getvalue()
    assert "mode ZERO_TORQUE   sim 0.05 s" in text
    assert "ticks 10  tick " in text
    for name in sim_robot.names:
        assert name in text
    assert "1 ZERO_TORQUE  2 DAMPING  3 STANDBY  4 LOCOMOTION  5 REMOTE  q quit" in text


def test_the_keys_line_offers_the_fault_reset_where_faults_latch(started):
    _, manager = started
    console = Console(file=io.StringIO(), width=200)
    console.print(LiveTable(manager, console=console, keys=True, reset_key=True).render())
    assert "5 REMOTE  r reset faults  q quit" in console.file.getvalue()


def test_r_asks_for_the_fault_reset():
    resets = []
    keys = ModeKeys(print, print, on_reset=lambda: resets.append(True))
    keys.press("r")
    keys.press("R")
    assert resets == [True, True]
    ModeKeys(print, print).press("r")  # where nothing latches, r does nothing


def test_live_table_shows_a_fault_from_the_tick_it_is_raised(started):
    system, manager = started
    console = Console(file=io.StringIO(), width=200)
    table = LiveTable(manager, console=console)
    system.set_flag("joint/left_elbow_pitch", "left_elbow_pitch: encoder lost")
    manager.tick()  # the same tick publishes it on /safety_status; the next refresh draws it
    console.print(table.render())
    assert "ERROR MujocoSystem/joint/left_elbow_pitch: left_elbow_pitch: encoder lost" in console.file.getvalue()


def test_working_shows_what_is_done_how_far_and_for_how_long_on_a_terminal_only():
    import io

    from rich.console import Console

    from humanoid_prime.cli._live import Working  # private to cli/: see the imports above

    screen = io.StringIO()
    terminal = Console(file=screen, force_terminal=True, width=100)
    with Working(terminal, "verifying the stops", total=4) as working:
        working.update("verifying the stops: left_elbow_pitch", completed=2)
        working.progress.refresh()
    drawn = screen.getvalue()
    assert "verifying the stops: left_elbow_pitch" in drawn and "50%" in drawn and "0:00:0" in drawn
    piped = io.StringIO()
    with Working(Console(file=piped, force_terminal=False), "bringing Prime up") as working:
        working.update("bringing Prime up: first tick done")
    assert piped.getvalue() == ""


def test_each_bringup_stage_is_told_as_it_completes():
    from humanoid_prime.runtime.session import BringupOptions, plan_session

    plan = plan_session(BringupOptions())
    told = []
    plan.on_stage = told.append
    plan.stage("virtual prime", plan.began)
    assert told == ["virtual prime"] and plan.stages[-1][0] == "virtual prime"


def test_live_table_names_each_configuration_file_with_its_sha256(started):
    from humanoid_prime.config.location import resolve_all

    _, manager = started
    manager.configuration = resolve_all().as_dict()
    console = Console(file=io.StringIO(), width=250)
    console.print(LiveTable(manager, console=console).render())
    text = console.file.getvalue()
    for kind, entry in manager.configuration.items():
        assert f"{kind:<11} {entry['path']}  sha256 {entry['sha256'][:12]}" in text


def rows(text: str) -> dict[str, list[str]]:
    """The table's rows by joint, split into cells (two spaces or more apart)."""
    import re

    cells = [re.split(r"\s{2,}", line.strip()) for line in text.splitlines()]
    return {row[0]: row[1:] for row in cells if row and row[0].startswith(("left_", "right_"))}


def test_live_table_shows_the_time_run_and_the_loop_rate_against_the_configured_one(started):
    system, manager = started
    Simulation(system, manager, realtime=False).run(0.5)
    manager.clock = lambda: manager.started_at + 12.34  # the run's clock, 12.34 s after its start
    console = Console(file=io.StringIO(), width=200)
    console.print(LiveTable(manager, console=console).render())
    assert "\nelapsed 12.3 s  loop 200.0 Hz of 200 Hz\n" in console.file.getvalue()  # the simulation's 200 Hz


def test_the_loop_rate_shown_is_the_one_the_loop_held_not_the_one_asked_for(started):
    _, manager = started
    for k in range(1, 301):  # a loop asked for 200 Hz that ticks every 25 ms; the table looks at its last second
        manager.tick(now=1000.0 + k * 0.025)
    console = Console(file=io.StringIO(), width=200)
    console.print(LiveTable(manager, console=console).render())
    assert " loop 40.0 Hz of 200 Hz\n" in console.file.getvalue()


def test_a_simulated_joint_has_no_drive_state_to_show(started):
    _, manager = started
    console = Console(file=io.StringIO(), width=200)
    console.print(LiveTable(manager, console=console).render())
    table = rows(console.file.getvalue())
    assert len(table) == 14
    assert all(cells[-3:] == ["—", "—", "—"] for cells in table.values())


def test_live_table_rows_show_each_erob_drives_statusword_state_al_state_and_torque(doubled):
    session = doubled.open()
    manager = session.manager
    console = Console(file=io.StringIO(), width=200)
    live = LiveTable(manager, console=console)
    doubled.master.torque_per_mille[3] = 100  # ring 3, left_elbow_pitch: a tenth of its 23 Nm
    doubled.master.fault(8, 0x8500)  # ring 8, right_elbow_pitch
    manager.tick()
    doubled.master.al_state[5] = 0x04  # ring 5, right_shoulder_pitch: the supervision found its slave in SAFE-OP
    console.print(live.render())
    table = rows(console.file.getvalue())
    assert table["left_shoulder_pitch"][-3:] == ["0x1637", "operation enabled", "OP"]
    assert table["left_elbow_pitch"][3] == "+2.30"  # tau Nm
    assert table["right_elbow_pitch"][-3:] == ["0x1208", "fault", "OP"]
    assert table["right_shoulder_pitch"][-3:] == ["0x1637", "operation enabled", "SAFE-OP"]
    assert table["left_wrist_roll"][-3:] == ["—", "—", "—"]  # a Sito wrist has no CiA402 drive
