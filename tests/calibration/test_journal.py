"""The record a gain override keeps while a drive is overridden, and the restore from it after its writer was
killed (``calibration.journal``, ``limp.restore_left``)."""

import json
import subprocess
import sys

import pytest

from doubles.mailboxes import DriveMailboxes
from humanoid_prime.calibration.journal import OverrideJournal, process_start
from humanoid_prime.calibration.limp import DampedLimp, restore_left
from humanoid_prime.errors import PrimeError

VIA = "socket /run/prime/control.sock"


def gains(drives, position):
    return {k: v for k, v in drives.values[position].items() if k != "window"}


def killed_limp(folder, position, via=VIA):
    """A process that recorded a limp of ``position`` (what the double's drive holds) and was killed outright."""
    script = ("import os, signal, sys; from pathlib import Path; "
              "from humanoid_prime.calibration.journal import OverrideJournal; "
              f"OverrideJournal(Path(sys.argv[1]), {via!r}, 'prime limp {position}').record("
              f"{position}, 'left_elbow_pitch', dict(gate=0, pos_reg=300, vel_reg=94, integral=5), {{}}, 'limp'); "
              "os.kill(os.getpid(), signal.SIGKILL)")
    assert subprocess.run([sys.executable, "-c", script, str(folder)]).returncode == -9


def limp_it(drives, position):
    drives.values[position].update(gate=1, pos_reg=0, integral=0)  # as the killed process left the drive


def test_the_record_is_written_before_the_first_write_and_removed_once_restored(tmp_path):
    drives = DriveMailboxes()
    journal = OverrideJournal(tmp_path, VIA, "prime limp 3")
    seen = []
    original = drives.sdo_write

    def spy(position, index, sub_index, data):
        seen.append([p.name for p in tmp_path.iterdir()])
        original(position, index, sub_index, data)

    drives.sdo_write = spy
    with DampedLimp(drives, 3, journal=(journal, "left_elbow_pitch")):
        record = json.loads(next(tmp_path.iterdir()).read_text())
    assert seen and all(len(names) == 1 for names in seen)  # there at every write, the first included
    assert record["found"] == {"gate": 0, "pos_reg": 300, "vel_reg": 94, "integral": 5}
    assert record["command"] == "prime limp 3" and record["left_as"] == "limp" and record["via"] == VIA
    assert list(tmp_path.iterdir()) == []


def test_a_record_that_cannot_be_kept_leaves_the_drive_as_it_is(tmp_path):
    drives = DriveMailboxes()
    before = gains(drives, 3)
    (tmp_path / "state").write_text("a file where the folder would be\n")
    with pytest.raises(PrimeError, match="ring 3: the drive is left as it is"), \
            DampedLimp(drives, 3, journal=(OverrideJournal(tmp_path / "state", VIA), "left_elbow_pitch")):
        pass
    assert gains(drives, 3) == before


def test_a_drive_whose_limp_was_killed_is_restored_as_found_and_said_once(tmp_path):
    drives = DriveMailboxes()
    before = gains(drives, 3)
    killed_limp(tmp_path, 3)
    limp_it(drives, 3)
    journal = OverrideJournal(tmp_path, VIA)
    [(position, line)] = restore_left(drives, journal)
    assert position == 3 and gains(drives, 3) == before
    assert line.startswith("ring 3 (left_elbow_pitch) was left limp by `prime limp 3` (pid ")
    assert line.endswith("which ended without restoring it: restored its gains as found, gate=0 pos_reg=300 "
                         "vel_reg=94 integral=5")
    assert restore_left(drives, journal) == [] and list(tmp_path.iterdir()) == []


def test_a_limp_still_running_is_left_alone(tmp_path):
    drives = DriveMailboxes()
    journal = OverrideJournal(tmp_path, VIA, "prime limp 3")
    with DampedLimp(drives, 3, journal=(journal, "left_elbow_pitch")):
        assert restore_left(drives, OverrideJournal(tmp_path, VIA)) == []  # this process is its writer
        assert drives.values[3]["pos_reg"] == 0


def test_a_pid_given_to_another_process_since_is_no_running_writer(tmp_path):
    drives = DriveMailboxes()
    journal = OverrideJournal(tmp_path, VIA, "prime limp 3")
    with DampedLimp(drives, 3, journal=(journal, "left_elbow_pitch")):
        path = next(tmp_path.iterdir())
        record = json.loads(path.read_text())
        path.write_text(json.dumps({**record, "started": process_start(record["pid"]) - 1}))  # same pid, not it
        assert [p for p, _ in restore_left(drives, OverrideJournal(tmp_path, VIA))] == [3]


def test_a_record_made_another_way_is_not_applied(tmp_path):
    drives = DriveMailboxes()
    killed_limp(tmp_path, 3, via="socket /tmp/a-virtual-run.sock")
    limp_it(drives, 3)
    assert restore_left(drives, OverrideJournal(tmp_path, VIA)) == []
    assert drives.values[3]["pos_reg"] == 0 and len(list(tmp_path.iterdir())) == 1


def test_a_drive_that_cannot_be_restored_keeps_its_record_and_is_one_line(tmp_path):
    drives = DriveMailboxes()
    killed_limp(tmp_path, 3)
    drives.dead.add(3)
    with pytest.raises(PrimeError) as error:
        restore_left(drives, OverrideJournal(tmp_path, VIA))
    assert "ring 3 (left_elbow_pitch) was left limp" in str(error.value) and "\n" not in str(error.value)
    assert "it could not be restored" in str(error.value) and len(list(tmp_path.iterdir())) == 1


def test_an_unreadable_record_is_one_line_naming_it(tmp_path):
    (tmp_path / "erob-ring3-gains-00000000.json").write_text("{not json")
    with pytest.raises(PrimeError, match="erob-ring3-gains-00000000.json: a record of a drive's gains that cannot "
                                         "be read"):
        restore_left(DriveMailboxes(), OverrideJournal(tmp_path, VIA))
