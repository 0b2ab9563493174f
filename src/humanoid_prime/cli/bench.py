"""``prime bench`` (and ``make bench``): measure the performance targets and print them against their goals."""

from __future__ import annotations

import argparse
import importlib
import json
import math
import operator
import time
from collections.abc import Callable
from typing import Any

from rich.table import Table

from humanoid_prime import bench as b
from humanoid_prime.cli._common import console as make_console
from humanoid_prime.cli._common import output_file
from humanoid_prime.cli._live import Working
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_text

SUITES: dict[str, tuple[str, str, str]] = {
    "sim": ("humanoid_prime.bench.sim", "bench_sim", "MujocoSystem + controllers, headless, as fast as possible"),
    "sito": ("humanoid_prime.bench.sito", "bench_sito", "SitoSystem read+write and bus load, 4 emulated wrists"),
    "ethercat": ("humanoid_prime.bench.ethercat", "bench_ethercat",
                 "EthercatSystem on the emulated ring: cold bring-up at 50 Hz and 1 kHz, cycle cost"),
    "bringup": ("humanoid_prime.bench.bringup", "bench_bringup",
                "prime bringup --emulate: 14 joints, mode switches, 50 Hz loop"),
    "dds": ("humanoid_prime.bench.dds", "bench_dds",
            "the simulated Prime at 50 Hz and 1 kHz with and without DDS, and a subscriber process"),
    "record": ("humanoid_prime.bench.dds", "bench_record",
               "the simulated Prime at 50 Hz and 1 kHz with and without --record"),
}

_OPS: dict[str, Callable[[float, float], bool]] = {"<=": operator.le, ">=": operator.ge}

# (suite, figure path, comparison, goal, what) -- DESIGN §6
TARGETS: tuple[tuple[str, str, str, float, str], ...] = (
    ("sim", "realtime_factor", ">=", b.TARGET_REALTIME_FACTOR, "simulation speed (x real time)"),
    ("sito", "host_load_percent", "<=", b.TARGET_LOAD_PERCENT, "Sito bus load from the host at 50 Hz (%)"),
    ("bringup", "bringup_seconds", "<=", b.TARGET_BRINGUP_S,
     "cold bring-up, 10 eRob to OP + 4 Sito, joint states flowing (s)"),
    ("bringup", "switch_seconds.max", "<=", b.TARGET_SWITCH_S, "mode switch, gains on all 10 eRob (s, worst)"),
    ("bringup", "skew_seconds.max", "<=", b.TARGET_SKEW_S, "mode switch skew between slaves (s, worst)"),
    ("bringup", "tick_us.median", "<=", b.TARGET_TICK_MEDIAN_US,
     "control tick, 14 joints, read+update+write (us, median)"),
    ("bringup", "tick_us.p99", "<=", b.TARGET_TICK_P99_US, "control tick, 14 joints (us, p99)"),
    ("bringup", "jitter_us.p99", "<=", b.TARGET_JITTER_P99_US, "loop period jitter at 50 Hz (us, p99)"),
    ("dds", "added_tick_us_median", "<=", b.TARGET_DDS_ADDED_TICK_US, "DDS: added tick cost (us, median, worst rate)"),
    ("dds", "overruns_with_dds", "<=", 0, "DDS: overruns at 50 Hz and 1 kHz"),
    ("record", "added_tick_us_median", "<=", b.TARGET_RECORD_ADDED_TICK_US,
     "recording: added tick cost (us, median, worst rate)"),
)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("bench", help="measure the performance targets",
                              description="Run the benchmarks and print each figure against its target. "
                                          "Suites: " + "; ".join(f"{k}: {v[2]}" for k, v in SUITES.items()))
    p.add_argument("--only", metavar="SUITE,...", help=f"run only these suites ({', '.join(SUITES)})")
    p.add_argument("--output", metavar="FILE", type=output_file, help="also write every figure as JSON")
    p.add_argument("--json", action="store_true", help="print every figure as JSON instead of the table")
    p.set_defaults(func=run)


def figure(results: dict[str, Any], suite: str, path: str) -> float | None:
    value: Any = results.get(suite)
    for key in path.split("."):
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    return float(value) if isinstance(value, (int, float)) else None


def run(args: argparse.Namespace) -> int:
    chosen = list(SUITES) if not args.only else [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = [s for s in chosen if s not in SUITES]
    if unknown:
        raise PrimeError(f"unknown suite {unknown[0]!r}; suites: {', '.join(SUITES)}")
    console = make_console(stderr=args.json)
    results: dict[str, Any] = {}
    for suite in chosen:
        module, function, what = SUITES[suite]
        console.print(f"[bold]{suite}[/bold]: {what} ...")
        began = time.monotonic()
        try:
            with Working(console, f"{suite}: measuring"):
                results[suite] = getattr(importlib.import_module(module), function)()
        except PrimeError as exc:
            results[suite] = {"error": str(exc)}
        results[suite]["bench_seconds"] = round(time.monotonic() - began, 1)
    if args.output:
        atomic_write_text(args.output, json.dumps(results, indent=2) + "\n")
    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    table = Table(title="Prime performance targets", title_justify="left", header_style="bold")
    for column in ("target", "measured", "goal", "met"):
        table.add_column(column, justify="left" if column == "target" else "right")
    for suite, path, op, goal, what in TARGETS:
        if suite not in results:
            continue
        value = figure(results, suite, path)
        note = results[suite].get("skipped") or results[suite].get("error")
        if value is None or not math.isfinite(value):
            table.add_row(what, note or "-", f"{op} {goal:g}", "[yellow]n/a[/yellow]")
            continue
        met = _OPS[op](value, goal)
        table.add_row(what, f"{value:.4g}", f"{op} {goal:g}", "[green]yes[/green]" if met else "[red]no[/red]")
    console.print(table)
    for suite, data in results.items():
        console.print(f"[bold]{suite}[/bold] {json.dumps(data)}", soft_wrap=True)
    return 0
