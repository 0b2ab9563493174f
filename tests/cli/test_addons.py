"""Add-ons: a new one is its module and one line in ``ADDONS``; a run attaches it, tears it down with the run's
stack, and puts its figures in the summary under its name."""

import json
import textwrap

import pytest

from humanoid_prime.cli import main
from humanoid_prime.cli.addons import ADDONS

PROBE = '''
"""A user's add-on: counts the run's ticks while it is attached."""


def options(parser):
    parser.add_argument("--probe", action="store_true", help="count the ticks")


def check(args):
    return args.probe


def attach(run, args, stack):
    seen = {"ticks": 0, "closed": False}

    def tick():
        seen["ticks"] += 1

    run.manager.add_end_of_tick(tick)
    stack.callback(lambda: seen.update(closed=True))
    stack.callback(run.manager.remove_end_of_tick, tick)
    run.report(f"probe: counting ticks of {run.title}")
    return lambda: dict(seen)
'''


@pytest.fixture
def probe(tmp_path, monkeypatch):
    (tmp_path / "prime_probe.py").write_text(textwrap.dedent(PROBE))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(ADDONS, "probe", "prime_probe")  # the one line


def sim(tmp_path, *args: str) -> dict:
    summary = tmp_path / "summary.json"
    assert main(["sim", "--socket", str(tmp_path / "control.sock"), "--mode", "DAMPING", "--duration", "0.2",
                 "--fast", "--summary", str(summary), *args]) == 0
    return json.loads(summary.read_text())


def test_a_registered_addon_is_attached_to_a_sim_run_and_summarised(probe, tmp_path, capsys):
    summary = sim(tmp_path, "--probe")
    assert summary["probe"] == {"ticks": summary["ticks"], "closed": True}
    assert summary["ticks"] == 40  # 0.2 simulated seconds at 200 Hz
    assert "probe: counting ticks of Prime (simulated)\n" in capsys.readouterr().out


def test_an_addon_the_user_did_not_ask_for_stays_out_of_the_run(probe, tmp_path):
    assert "probe" not in sim(tmp_path)
