"""``bench_startup``: each command's start-up from the shell, beside the interpreter's own in the same run."""

import pytest

from humanoid_prime.bench.startup import COMMANDS, bench_startup

pytestmark = pytest.mark.realtime  # start-up times, measured


def test_bench_startup_times_every_command_beside_python_c_pass():
    result = bench_startup(runs=1)
    floor = result["floors"]["python_s"]["median"]
    for name in COMMANDS:
        figure = result[f"{name}_s"]
        assert floor < figure["median"] <= figure["max"], (name, result)
        assert result["cpu_s"][name] > 0
    assert set(COMMANDS) == {"help", "info", "switch", "decode"}
    assert result["info_first_run_s"] > 0
    assert result["bytecode"].startswith(("compiled ahead", "compiled at every start"))
