"""`prime config init|show`, and every command that writes a file keeps out of the installed package."""

from __future__ import annotations

import json

import pytest

from humanoid_prime.cli import main
from humanoid_prime.files import bundled, package_root


@pytest.fixture
def home(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    for name in ("XDG_CONFIG_HOME", "PRIME_CONFIG_DIR", "PRIME_ROBOT"):
        monkeypatch.delenv(name, raising=False)
    return tmp_path / ".config" / "prime"


def test_init_copies_the_templates_and_show_then_names_them(home, capsys):
    assert main(["config", "init"]) == 0
    for name in ("prime_hardware.yaml", "prime_calibration.yaml", "prime_controllers.yaml"):
        assert (home / name).read_bytes() == bundled(name).read_bytes()
    capsys.readouterr()
    assert main(["config", "show", "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["folder"] == str(home) and shown["folder_exists"]
    assert {shown[k]["path"] for k in ("hardware", "calibration", "controllers")} == {
        str(home / n) for n in ("prime_hardware.yaml", "prime_calibration.yaml", "prime_controllers.yaml")}


def test_init_keeps_a_file_that_is_already_there(home, capsys):
    home.mkdir(parents=True)
    (home / "prime_hardware.yaml").write_text("# mine\n")
    assert main(["config", "init", "--json"]) == 0
    rows = {r["kind"]: r["action"] for r in json.loads(capsys.readouterr().out)["files"]}
    assert rows == {"hardware": "kept", "calibration": "written", "controllers": "written"}
    assert (home / "prime_hardware.yaml").read_text() == "# mine\n"


def test_init_with_a_robot_name_makes_its_subfolder(home):
    assert main(["config", "init", "--robot", "alpha"]) == 0
    assert (home / "alpha" / "prime_calibration.yaml").is_file()
    assert main(["info", "--robot", "alpha", "--json"]) == 0


def test_a_command_on_a_robot_nobody_created_says_how_to_create_it(home, capsys):
    assert main(["info", "--robot", "alpah"]) == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("prime info: no configuration folder ") and "prime config init --robot alpah" in line


def test_flip_on_a_fresh_machine_writes_the_robots_own_copy_not_the_template(home, capsys):
    before = bundled("prime_calibration.yaml").read_bytes()
    assert main(["calibration", "flip", "left_elbow_pitch"]) == 0
    assert bundled("prime_calibration.yaml").read_bytes() == before
    assert f"wrote {home / 'prime_calibration.yaml'}" in capsys.readouterr().out
    assert main(["info", "--json"]) == 0
    rows = {r["joint"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows["left_elbow_pitch"]["direction"] == -1  # the next command reads what flip wrote


def status(argv: list[str]) -> int:
    """The exit status of a command, whether it returned it or argparse exited with it."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code)


@pytest.mark.parametrize("command", [
    ["calibration", "flip", "left_elbow_pitch", "--calibration", "{data}/prime_calibration.yaml"],
    ["calibration", "fold", "--output", "{data}/folded"],
    ["sim", "--fast", "--duration", "0.1", "--summary", "{data}/summary.json"],
    ["sim", "--fast", "--duration", "0.1", "--record", "{data}/run.mcap"],
    ["calibrate", "--output", "{data}/prime_calibration.yaml"],
    ["bench", "--only", "sim", "--output", "{data}/bench.json"],
])
def test_a_command_asked_to_write_inside_the_package_refuses_and_writes_nothing(home, capsys, command):
    data = package_root() / "data"
    before = {p.name: p.read_bytes() for p in data.iterdir() if p.is_file()}
    assert status([part.format(data=data) for part in command]) != 0
    assert "inside the installed package" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in data.iterdir() if p.is_file()} == before
