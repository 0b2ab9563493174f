"""Command-line start-up (DESIGN §6): ``prime --help``, ``prime info``, ``prime switch`` and ``prime decode`` from
the shell to their exit, each beside ``python -c pass`` (the interpreter's own start, the floor) in the same run.

Every command runs as its own process with the environment as it is (``PYTHONDONTWRITEBYTECODE`` included: the
figures say whether the package's bytecode was compiled ahead or is compiled at every start), interleaved with the
floor so a swing of the host moves all of them alike. ``prime switch`` asks a control socket served here, which
answers at once: the figure is the command's own cost, not a mode switch's. ``prime info`` reads the robot's
description from the user's cache once it has been expanded; its first run, with an empty cache, is shown too.
"""

from __future__ import annotations

import importlib.util
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.socket import SOCKET_ENV, ControlServer

COMMANDS: dict[str, list[str]] = {
    "help": ["--help"],
    "info": ["info"],
    "switch": ["switch", "STANDBY"],
    "decode": ["decode", "statusword", "5687"],
}


def prime_command() -> list[str]:
    """``prime`` as the user runs it: the script installed beside this interpreter."""
    script = Path(sys.executable).with_name("prime")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "humanoid_prime"]


def bench_startup(runs: int = 9) -> dict[str, object]:
    """Each command's wall time over ``runs`` runs, and the floor's, measured round-robin."""
    prime = prime_command()
    with tempfile.TemporaryDirectory(prefix="prime-bench-") as tmp, \
            ControlServer(lambda mode, wait: {"mode": mode.value, "outcome": "active", "active": mode.value},
                          Path(tmp) / "control.sock"):
        env = {**os.environ, SOCKET_ENV: str(Path(tmp) / "control.sock")}
        info_first = _timed([*prime, "info"], {**env, "XDG_CACHE_HOME": str(Path(tmp) / "cache")})
        argvs = {"floor": [sys.executable, "-c", "pass"], **{name: [*prime, *args] for name, args in COMMANDS.items()}}
        for argv in argvs.values():  # once untimed: the disk cache and the description's cache filled
            _timed(argv, env)
        times: dict[str, list[float]] = {name: [] for name in argvs}
        cpu: dict[str, list[float]] = {name: [] for name in argvs}
        for _ in range(runs):
            for name, argv in argvs.items():
                before = _children_cpu_s()
                times[name].append(_timed(argv, env))
                cpu[name].append(_children_cpu_s() - before)
    figures = {f"{name}_s": _stats(samples) for name, samples in times.items() if name != "floor"}
    return {
        **figures,
        # the processor time each took, which a busy host does not stretch as it does the wall time
        "cpu_s": {name: round(statistics.median(samples), 3) for name, samples in cpu.items()},
        "info_first_run_s": round(info_first, 3),
        "floors": {"python_s": _stats(times["floor"])},
        "runs": runs,
        "bytecode": bytecode_state(),
        "command": " ".join(prime),
    }


def bytecode_state() -> str:
    """Whether the package's modules start from compiled bytecode or are compiled at every start."""
    import humanoid_prime

    source = humanoid_prime.__file__ or ""
    cached = importlib.util.cache_from_source(source)
    fresh = os.path.exists(cached) and os.path.getmtime(cached) >= os.path.getmtime(source)
    writes = "not written (PYTHONDONTWRITEBYTECODE)" if sys.dont_write_bytecode or \
        os.environ.get("PYTHONDONTWRITEBYTECODE") else "written on first use"
    return f"{'compiled ahead' if fresh else 'compiled at every start'}; bytecode {writes}"


def _timed(argv: list[str], env: dict[str, str]) -> float:
    began = time.perf_counter()
    proc = subprocess.run(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=60)
    elapsed = time.perf_counter() - began
    if proc.returncode != 0:
        last = proc.stderr.strip().splitlines()
        raise PrimeError(f"{' '.join(argv)} failed (exit {proc.returncode}): {last[-1] if last else 'no output'}")
    return elapsed


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _stats(samples: list[float]) -> dict[str, float]:
    return {"median": round(statistics.median(samples), 3), "max": round(max(samples), 3)}
