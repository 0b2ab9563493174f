"""`prime bench`: runs the chosen suites and reports each figure against its DESIGN §6 target."""

import json

import pytest

from humanoid_prime.cli import main
from humanoid_prime.cli.bench import TARGETS, figure


def test_unknown_suite_is_one_line_error(capsys):
    assert main(["bench", "--only", "warp"]) == 1
    err = capsys.readouterr().err
    assert "unknown suite 'warp'" in err and err.count("\n") == 1


@pytest.mark.realtime  # a wall-clock figure: faster than real time
def test_sim_suite_reports_the_realtime_factor(capsys, tmp_path):
    out = tmp_path / "bench.json"
    assert main(["bench", "--only", "sim", "--json", "--output", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text())
    assert printed["sim"]["realtime_factor"] > 1.0
    assert printed["sim"]["modes_visited"][0] == "ZERO_TORQUE"


def test_figures_are_found_by_dotted_path():
    results = {"bringup": {"tick_us": {"median": 87.0}}}
    assert figure(results, "bringup", "tick_us.median") == 87.0
    assert figure(results, "bringup", "jitter_us.p99") is None
    assert {suite for suite, *_ in TARGETS} == {"startup", "sim", "sito", "bringup", "khz", "dds", "record", "doctor",
                                                "gate"}


def test_every_floor_stands_beside_a_figure_with_a_target_and_comes_from_a_suite_of_the_bench():
    from humanoid_prime.cli.bench import FLOORS, SUITES

    judged = {(suite, path) for suite, path, *_ in TARGETS}
    assert set(FLOORS) <= judged
    assert {suite for suite, _path, _what in FLOORS.values()} <= set(SUITES)
    # the 50 Hz tick beside the same tick at 1 kHz (warm caches), in the same run
    assert FLOORS["bringup", "tick_cpu_us.median"][:2] == ("khz", "tick_cpu_us.median")
