"""1 kHz on the emulated robot (DESIGN §6: 60 s with no overrun), and beside it the machine's own real-time
latency, measured right after the run for as long again by ``cyclictest`` (Debian's rt-tests), the field's
standard probe.

The run is ``prime bringup --emulate --rate 1000 --cpu 0``: the control loop at ``SCHED_FIFO`` 80 on CPU 0,
the emulated robot at 70 on the other CPUs. Then ``cyclictest`` keeps one thread on every CPU at ``SCHED_FIFO``
90 that wakes every millisecond and records how late it woke. It sees the kernel and the virtual machine, not
our threads. A wake-up a whole period late is a stall that no code above the kernel can avoid: on the loop's
CPU it delays a tick, and on the emulated robot's a reply. The number of such wake-ups is the floor shown
beside the overruns. The probe runs after the loop, not during it: on a virtual machine, the loop overran
about twice as often with the probe's wake-ups beside it on both CPUs.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
from collections.abc import Mapping
from pathlib import Path

from humanoid_prime.bench.bringup import emulated_bringup, json_object
from humanoid_prime.errors import PrimeError

RATE_HZ = 1000.0
DURATION_S = 60.0
PROBE_PRIORITY = 90  # above the control loop's 80: what the machine gives a real-time thread
PROBE = "cyclictest"


def machine_latency(seconds: float, *, interval_us: int = 1000, late_us: int = 1000
                    ) -> tuple[dict[int, dict[str, int]] | None, str]:
    """``cyclictest`` on every CPU for ``seconds``, waking each ``interval_us``: per CPU the wake-ups, the worst
    lateness (us) and how many wake-ups were at least ``late_us`` late, with what was run; or None with the
    reason nothing was measured (the probe is not installed, or may not run at real-time priority here)."""
    executable = shutil.which(PROBE)
    if executable is None:
        return None, f"{PROBE} is not installed (Debian package rt-tests)"
    with tempfile.TemporaryDirectory(prefix="prime-bench-") as tmp:
        path = Path(tmp) / "latency.json"
        # -S: a thread per CPU, pinned; -m: locked memory; -h: a histogram of lateness in us, up to late_us
        try:
            proc = subprocess.run([executable, "-S", "-m", "-q", "-p", str(PROBE_PRIORITY), "-i", str(interval_us),
                                   "-D", str(max(1, round(seconds))), "-h", str(late_us), f"--json={path}"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                  timeout=seconds + 60.0)
        except subprocess.TimeoutExpired:
            return None, f"{PROBE} did not end within a minute of its {seconds:g} s"
        if proc.returncode != 0 or not path.exists():
            last = proc.stderr.strip().splitlines()
            return None, f"{PROBE} measured nothing (exit {proc.returncode}): {last[-1] if last else 'no output'}"
        per_cpu = per_cpu_latency(json.loads(path.read_text()))
    return per_cpu, (f"{PROBE} at SCHED_FIFO {PROBE_PRIORITY} on {len(per_cpu)} CPUs for {seconds:g} s after the "
                     f"run, waking every {interval_us} us; late: >= {late_us} us")


def per_cpu_latency(report: object) -> dict[int, dict[str, int]]:
    """Per CPU from cyclictest's JSON, whose histogram holds the wake-ups under its bound, a bucket a us."""
    threads = json_object(report).get("thread")
    if not isinstance(threads, dict):
        raise PrimeError(f"{PROBE}'s JSON has no per-thread figures")
    per_cpu = {}
    for value in threads.values():
        thread = json_object(value)
        on_time = sum(_whole(count) for count in json_object(thread.get("histogram")).values())
        cycles = _whole(thread.get("cycles"))
        per_cpu[_whole(thread.get("cpu"))] = {"wakeups": cycles, "max_us": _whole(thread.get("max")),
                                              "late": cycles - on_time}
    return dict(sorted(per_cpu.items()))


def _whole(value: object) -> int:
    """A count in cyclictest's JSON (a number, or a string of one)."""
    if isinstance(value, (int, float, str)):
        return int(value)
    raise PrimeError(f"{PROBE}'s JSON holds {value!r} where it holds a count")


def bench_khz(duration: float = DURATION_S, *, cpu: int = 0, timeout: float | None = None) -> dict[str, object]:
    summary = emulated_bringup(["--rate", f"{RATE_HZ:g}", "--cpu", str(cpu), "--duration", f"{duration:g}"],
                               timeout=timeout if timeout is not None else duration + 120.0)
    return khz_figures(summary, *machine_latency(duration), cpu=cpu, duration=duration)


def khz_figures(summary: Mapping[str, object], machine: dict[int, dict[str, int]] | None, probe: str, *, cpu: int,
                duration: float) -> dict[str, object]:
    return {
        "rate_hz": summary["update_rate"],
        "duration_s": duration,
        "cpu": cpu,
        "ok": summary["ok"],
        "problems": summary["problems"],
        "ticks": summary["ticks"],
        "overruns": summary["overruns"],
        "tick_us": summary["tick_us"],
        "tick_cpu_us": summary["tick_cpu_us"],
        "tick_io_us": summary["tick_io_us"],
        "jitter_us": summary["jitter_us"],
        "realtime": summary.get("realtime", {}),
        "floors": {
            # the probe's threads, one a CPU, each waking every period: how many woke a period or more late
            "machine_late_wakeups": sum(c["late"] for c in machine.values()) if machine is not None else None,
            "machine": {str(k): v for k, v in machine.items()} if machine is not None else None,
            "machine_probe": probe,
            "loop_cpu_late_wakeups": machine.get(cpu, {}).get("late") if machine is not None else None,
        },
        "emulator": json_object(summary["emulator"]).get("process"),  # where the emulated robot ran, from the kernel
    }
