"""Where a robot's configuration lives: the same rule for every file and every command (config.location)."""

from __future__ import annotations

from pathlib import Path

import pytest

from humanoid_prime.config.location import FILE_NAMES, KINDS, resolve_all, template, write_target
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_text, bundled, package_root


@pytest.fixture
def env(tmp_path, monkeypatch) -> Path:
    """A fresh HOME with no configuration and no PRIME_* variables."""
    monkeypatch.setenv("HOME", str(tmp_path))
    for name in ("XDG_CONFIG_HOME", "PRIME_CONFIG_DIR", "PRIME_ROBOT"):
        monkeypatch.delenv(name, raising=False)
    return tmp_path


def populate(folder: Path, *kinds: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for kind in kinds:
        (folder / FILE_NAMES[kind]).write_bytes(template(kind).read_bytes())


def test_with_nothing_configured_every_file_is_the_bundled_template(env):
    files = resolve_all()
    assert files.folder.path == env / ".config" / "prime"
    for c in files:
        assert c.template and c.path == bundled(FILE_NAMES[c.kind])
        assert "bundled template" in c.why and str(env / ".config" / "prime") in c.why


def test_the_default_folder_wins_over_the_template_file_by_file(env):
    populate(env / ".config" / "prime", "calibration")
    files = resolve_all()
    assert files.calibration.path == env / ".config" / "prime" / "prime_calibration.yaml"
    assert not files.calibration.template and files.calibration.why == "~/.config/prime"
    assert files.hardware.template and files.controllers.template


def test_xdg_config_home_moves_the_default_folder(env, monkeypatch):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(env / "xdg"))
    populate(env / "xdg" / "prime", *KINDS)
    files = resolve_all()
    assert all(c.path.parent == env / "xdg" / "prime" and c.why == "$XDG_CONFIG_HOME/prime" for c in files)


def test_prime_config_dir_is_the_folder_and_must_exist(env, monkeypatch):
    monkeypatch.setenv("PRIME_CONFIG_DIR", str(env / "lab"))
    with pytest.raises(PrimeError, match=r"no configuration folder .*lab.*\$PRIME_CONFIG_DIR.*prime config init"):
        resolve_all()
    populate(env / "lab", "hardware")
    assert resolve_all().hardware.path == env / "lab" / "prime_hardware.yaml"


def test_a_named_robot_is_a_subfolder_that_must_exist(env, monkeypatch):
    with pytest.raises(PrimeError, match=r"robot 'beta' \(--robot\).*prime config init --robot beta"):
        resolve_all("beta")
    populate(env / ".config" / "prime" / "beta", "calibration")
    assert resolve_all("beta").calibration.path == env / ".config" / "prime" / "beta" / "prime_calibration.yaml"
    monkeypatch.setenv("PRIME_ROBOT", "beta")
    files = resolve_all()
    assert files.calibration.path.parent.name == "beta" and "$PRIME_ROBOT" in files.calibration.why


@pytest.mark.parametrize("name", ["../etc", "", "a/b", "-x"])
def test_a_robot_name_is_a_plain_folder_name(env, name):
    with pytest.raises(PrimeError, match="a robot name is"):
        resolve_all(name)


def test_a_file_given_on_the_command_line_wins_and_is_never_rewritten_elsewhere(env, tmp_path):
    given = tmp_path / "mine.yaml"
    files = resolve_all(calibration=given)
    assert files.calibration.path == given and files.calibration.why == "--calibration"
    assert write_target(files.calibration, files.folder) == given


def test_a_template_is_rewritten_as_the_robots_own_copy(env):
    files = resolve_all()
    assert write_target(files.calibration, files.folder) == env / ".config" / "prime" / "prime_calibration.yaml"


def test_nothing_is_ever_written_inside_the_installed_package(env):
    files = resolve_all(calibration=bundled("prime_calibration.yaml"))
    with pytest.raises(PrimeError, match="inside the installed package"):
        write_target(files.calibration, files.folder)
    with pytest.raises(PrimeError, match="inside the installed package"):
        atomic_write_text(package_root() / "data" / "anything.yaml", "x")
    assert not (package_root() / "data" / "anything.yaml").exists()


def test_each_file_is_named_with_its_sha256(env):
    import hashlib

    files = resolve_all()
    entry = files.as_dict()["controllers"]
    assert entry["sha256"] == hashlib.sha256(bundled("prime_controllers.yaml").read_bytes()).hexdigest()
    assert entry["template"] is True and entry["path"] == str(bundled("prime_controllers.yaml"))
