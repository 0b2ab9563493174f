"""``prime sim``: the demonstration visits every mode; options and bad input behave."""

import json

import pytest

from humanoid_prime.cli import main
from humanoid_prime.modes import Mode


def run_sim(tmp_path, *args: str) -> int:
    return main(["sim", "--socket", str(tmp_path / "control.sock"), *args])


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("demo")
    summary = tmp_path / "summary.json"
    code = run_sim(tmp_path, "--duration", "20", "--fast", "--summary", str(summary))
    return code, json.loads(summary.read_text())


def test_the_demonstration_exits_zero(demo):
    assert demo[0] == 0


def test_the_demonstration_visits_every_mode_in_order(demo):
    assert demo[1]["modes_visited"] == ["ZERO_TORQUE", "DAMPING", "STANDBY", "LOCOMOTION", "REMOTE", "DAMPING"]
    assert set(demo[1]["modes_visited"]) == set(Mode)


def test_the_demonstration_has_no_fallbacks(demo):
    assert demo[1]["fallbacks"] == []


def test_the_summary_counts_20_simulated_seconds_at_200_hz(demo):
    summary = demo[1]
    assert summary["sim_seconds"] == 20.0
    assert summary["ticks"] == 4000
    assert (summary["update_rate"], summary["physics_rate"]) == (200.0, 1000.0)


def test_the_summary_reports_timing(demo):
    summary = demo[1]
    assert summary["wall_seconds"] > 0
    assert summary["realtime_factor"] == pytest.approx(summary["sim_seconds"] / summary["wall_seconds"], rel=1e-3)
    assert 0 < summary["tick_us"]["median"] <= summary["tick_us"]["p99"]


def test_without_a_terminal_each_mode_gets_one_progress_line(tmp_path, capsys):
    assert run_sim(tmp_path, "--duration", "20", "--fast") == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("staged start: hardware configure -> joint_state_broadcaster "
                               "-> zero_torque_controller -> ")
    assert lines[0].split(" -> ")[-2:][0] == "hardware activate"
    progress = [line.split()[2] for line in lines[1:-1]]
    assert progress == ["ZERO_TORQUE", "DAMPING", "STANDBY", "LOCOMOTION", "REMOTE", "DAMPING"]
    assert lines[-1].startswith("visited ZERO_TORQUE -> DAMPING -> STANDBY -> LOCOMOTION -> REMOTE -> DAMPING | 4000")


def test_mode_option_stays_in_that_mode(tmp_path):
    summary = tmp_path / "s.json"
    assert run_sim(tmp_path, "--mode", "standby", "--duration", "1", "--fast", "--summary", str(summary)) == 0
    data = json.loads(summary.read_text())
    assert data["modes_visited"] == ["ZERO_TORQUE", "STANDBY"]
    assert data["final_mode"] == "STANDBY"
    assert data["ticks"] == 200


def test_json_option_prints_the_summary(tmp_path, capsys):
    assert run_sim(tmp_path, "--duration", "0.5", "--fast", "--json") == 0
    data = json.loads(capsys.readouterr().out)
    assert data["ticks"] == 100
    assert data["stopped_by"] == "duration"


def test_an_unknown_mode_is_one_line_and_exit_1(tmp_path, capsys):
    assert run_sim(tmp_path, "--mode", "FLY") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("prime sim: unknown mode 'FLY'")


def test_a_non_positive_duration_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        run_sim(tmp_path, "--duration", "0")
    assert exit_.value.code == 2
    assert "argument --duration: must be above 0, got 0" in capsys.readouterr().err


def test_viewer_without_a_display_is_one_line_and_exit_1(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert run_sim(tmp_path, "--viewer", "--duration", "1", "--fast") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "--viewer needs a display" in err


def test_viewer_on_a_display_that_does_not_answer_is_one_line_and_exit_1(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DISPLAY", ":4242")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert run_sim(tmp_path, "--viewer", "--duration", "1", "--fast") == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("prime sim: cannot open the MuJoCo viewer: ")
