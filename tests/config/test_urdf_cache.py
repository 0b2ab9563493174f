"""The expanded description is kept in the user's cache folder and used only while every file it came from is
unchanged; a cache that cannot be read or written costs time, never a wrong robot."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import xacro

from humanoid_prime.config.description import XACRO_FILE, render_urdf
from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.config.urdf_cache import cache_folder
from humanoid_prime.files import bundled, package_root

ARM = "prime_dummy.arm.xacro"


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache" / "prime" / "urdf"


@pytest.fixture
def description(tmp_path) -> Path:
    """A copy of the bundled description (its top file) and of the hardware file, to edit."""
    shutil.copytree(bundled(XACRO_FILE).parent, tmp_path / "description")
    shutil.copy(bundled("prime_hardware.yaml"), tmp_path / "prime_hardware.yaml")
    return tmp_path / "description" / Path(XACRO_FILE).name


def no_expansion(*args, **kwargs):
    raise AssertionError("xacro ran although the cache held this description")


def test_a_description_is_expanded_once_then_read_from_the_users_cache(cache, robot, monkeypatch):
    first = render_urdf(robot.hardware)
    assert cache_folder() == cache and len(list(cache.glob("*.json"))) == 1
    assert package_root() not in cache.parents
    sim = render_urdf(robot.hardware, use_sim=True)  # the arguments are part of the key
    assert sim != first and len(list(cache.glob("*.json"))) == 2
    monkeypatch.setattr(xacro, "process_file", no_expansion)
    assert render_urdf(robot.hardware) == first
    assert render_urdf(robot.hardware, use_sim=True) == sim


@pytest.mark.parametrize("edited", ["include", "hardware file"])
def test_an_edited_file_that_the_expansion_read_is_expanded_again(cache, description, edited):
    hardware_path = description.parent.parent / "prime_hardware.yaml"
    before = render_urdf(load_hardware(hardware_path), xacro_file=description)
    if edited == "include":
        arm = description.parent / ARM
        arm.write_text(arm.read_text().replace('effort="4.8"', 'effort="4.7"', 1))
        changed = 'effort="4.7"'
    else:
        hardware_path.write_text(hardware_path.read_text().replace("channel: can2", "channel: can7", 1))
        changed = ">can7<"
    assert changed not in before
    after = render_urdf(load_hardware(hardware_path), xacro_file=description)
    assert changed in after


def test_a_damaged_entry_is_expanded_again(cache, robot):
    first = render_urdf(robot.hardware)
    (entry,) = cache.glob("*.json")
    entry.write_text('{"format": 1, "reads": {}, "urdf": "')
    assert render_urdf(robot.hardware) == first


def test_a_cache_folder_that_cannot_be_written_costs_only_the_time(tmp_path, robot, monkeypatch):
    (tmp_path / "not-a-folder").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "not-a-folder"))
    assert "<robot" in render_urdf(robot.hardware)


def test_the_cache_keeps_only_its_newest_entries(cache, robot, monkeypatch):
    import humanoid_prime.config.urdf_cache as urdf_cache

    monkeypatch.setattr(urdf_cache, "KEPT_ENTRIES", 2)
    for rate in (50.0, 100.0, 200.0):
        render_urdf(robot.hardware, control_frequency=rate)
    assert len(list(cache.glob("*.json"))) == 2
