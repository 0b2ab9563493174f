"""The robot's config folder holding, where one of its three files belongs, something that is no file: a folder,
a symlink to nothing. Every command that reads the folder refuses with one line naming the path and what is
there, instead of running on the bundled template in silence; ``config init`` neither says "kept" nor writes the
other two files."""

from __future__ import annotations

import os

import pytest

from cli.bad_input.harness import check

FILES = {"hardware": "prime_hardware.yaml", "calibration": "prime_calibration.yaml",
         "controllers": "prime_controllers.yaml"}
PLACES = {  # what stands where the file belongs -> how to make it, what the line must say
    "a folder": (lambda path: path.mkdir(), "is a folder"),
    "a broken symlink": (lambda path: path.symlink_to(path.parent / "gone.yaml"), "broken symlink to"),
}
COMMANDS = {
    "info": ["info"],
    "config show": ["config", "show"],
    "config init": ["config", "init"],
    "calibration flip": ["calibration", "flip", "left_elbow_pitch"],
    "bringup": ["bringup", "--summary", "{tmp}/summary.json"],
}


@pytest.fixture
def robot_folder(folder, monkeypatch):
    """The case folder's ``robot/``: the robot's config folder ($PRIME_CONFIG_DIR)."""
    monkeypatch.setenv("PRIME_CONFIG_DIR", str(folder / "robot"))
    (folder / "robot").mkdir()
    return folder / "robot"


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("place", PLACES)
@pytest.mark.parametrize("kind", FILES)
def test_a_robot_file_that_is_no_file_is_one_line_naming_it(folder, robot_folder, monkeypatch, kind, place,
                                                            command):
    make, says = PLACES[place]
    path = robot_folder / FILES[kind]
    make(path)
    check(COMMANDS[command], folder, monkeypatch, needles=(str(path), says))
    assert sorted(os.listdir(robot_folder)) == [FILES[kind]], "a file was written beside it"


def test_a_robot_folder_that_is_a_broken_symlink_is_one_line(folder, monkeypatch):
    (folder / "robot").symlink_to(folder / "gone")
    monkeypatch.setenv("PRIME_CONFIG_DIR", str(folder / "robot"))
    check(["info"], folder, monkeypatch, needles=(str(folder / "robot"), "broken symlink"))
