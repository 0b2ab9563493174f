"""``prime bench`` (and ``make bench``): measure the performance targets and print them against their goals."""

from __future__ import annotations

import argparse
import importlib
import json
import math
import operator
import time
from collections.abc import Callable, Mapping

from rich.console import Console
from rich.table import Table

from humanoid_prime import bench as b
from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import LONGEST_S, cpu_number, member, members, output_file, real
from humanoid_prime.cli._common import console as make_console
from humanoid_prime.cli._live import Working
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_text

SUITES: dict[str, tuple[str, str, str]] = {
    "startup": ("humanoid_prime.bench.startup", "bench_startup",
                "prime --help, info, switch and decode, each from the shell to its exit, beside python -c pass"),
    "sim": ("humanoid_prime.bench.sim", "bench_sim", "MujocoSystem + controllers, headless, as fast as possible"),
    "sito": ("humanoid_prime.bench.sito", "bench_sito", "SitoSystem read+write and bus load, 4 emulated wrists"),
    "ethercat": ("humanoid_prime.bench.ethercat", "bench_ethercat",
                 "EthercatSystem on the emulated ring: cold bring-up at 50 Hz and 1 kHz, cycle cost"),
    "bringup": ("humanoid_prime.bench.bringup", "bench_bringup",
                "prime bringup --emulate: 14 joints, mode switches, 50 Hz loop"),
    "khz": ("humanoid_prime.bench.khz", "bench_khz",
            "prime bringup --emulate at 1 kHz for 60 s, then the machine's own real-time latency (cyclictest)"),
    "dds": ("humanoid_prime.bench.dds", "bench_dds",
            "the simulated Prime at 50 Hz and 1 kHz with and without DDS, and a subscriber process"),
    "record": ("humanoid_prime.bench.dds", "bench_record",
               "the simulated Prime at 50 Hz and 1 kHz with and without --record"),
    "doctor": ("humanoid_prime.bench.doctor", "bench_doctor",
               "prime doctor --emulate --backends ec,can, twice: start-up plus checks, beside the emulator's start"),
    "gate": ("humanoid_prime.bench.gate", "bench_gate",
             "the simulated Prime at 50 Hz in REMOTE, its gate with and without the body check, in turns"),
}

_OPS: dict[str, Callable[[float, float], bool]] = {"<=": operator.le, ">=": operator.ge}

# (suite, figure path) -> (suite, floor path, what the floor is): the physical limit shown beside a figure
FLOORS: dict[tuple[str, str], tuple[str, str, str]] = {
    **{("startup", f"{command}_s.median"): ("startup", "floors.python_s.median",
                                            "python -c pass in this run (s, median)")
       for command in ("help", "info", "switch", "decode")},
    ("sim", "realtime_factor"): ("sim", "floors.realtime_factor", "MuJoCo's own steps in this run"),
    ("bringup", "tick_io_us.median"): ("bringup", "floors.ethercat_cycle_us",
                                       "EtherCAT frame on the wire, 10 slaves at 100 Mbit/s"),
    # At 50 Hz the emulated robot runs on the same two cores between ticks and each tick starts with cold caches;
    # at 1 kHz the same tick finds them warm: what the code costs, beside what this machine makes of it.
    ("bringup", "tick_cpu_us.median"): ("khz", "tick_cpu_us.median",
                                        "the same tick at 1 kHz, caches warm, in this run (us, median)"),
    ("record", "added_tick_us_median"): ("dds", "floors.tap_added_tick_us_median",
                                         "handing each tick to another thread, nothing done, in the DDS runs"),
    **{("dds", f"{rate}_hz.{backend}added_tick_us_median"): (
        "dds", f"{rate}_hz.tap_added_tick_us_median", "handing each tick to the publisher thread, nothing published")
       for rate in (50, 1000) for backend in ("", "rclpy_")},
    ("doctor", "seconds.median"): ("doctor", "floors.seconds",
                                   "python -c pass twice (it re-executes in its namespace) + its fixed waits (s)"),
    ("gate", "added_tick_us_median"): ("gate", "floors.tick_cpu_us_median",
                                       "the same tick without the body check, in this run (us, median)"),
    ("khz", "overruns"): ("khz", "floors.machine_late_wakeups",
                          "the machine's own: real-time wake-ups a period or more late, all CPUs, "
                          "in as long again right after the run (cyclictest)"),
}

# (suite, figure path, comparison, goal, what) -- DESIGN §6
TARGETS: tuple[tuple[str, str, str, float, str], ...] = (
    *(("startup", f"{command}_s.median", "<=", b.TARGET_STARTUP_S, f"{line} start-up (s, median)")
      for command, line in (("help", "prime --help"), ("info", "prime info"), ("switch", "prime switch"),
                            ("decode", "prime decode"))),
    ("startup", "info_first_run_s", "<=", math.inf, "prime info's first run, the description not yet cached (s)"),
    ("sim", "floor_fraction", ">=", b.TARGET_FLOOR_FRACTION,
     "simulation speed as a fraction of MuJoCo's own in this run"),
    ("sim", "realtime_factor", "<=", math.inf, "simulation speed (x real time)"),
    ("sito", "host_load_percent", "<=", b.TARGET_LOAD_PERCENT, "Sito bus load from the host at 50 Hz (%)"),
    ("bringup", "bringup_seconds", "<=", b.TARGET_BRINGUP_S,
     "cold bring-up, 10 eRob to OP + 4 Sito, joint states flowing (s)"),
    ("bringup", "emulator_start_seconds", "<=", math.inf,
     "starting the emulated robot itself, before the bring-up (s, the robot's power switch)"),
    ("bringup", "switch_seconds.max", "<=", b.TARGET_SWITCH_S, "mode switch, gains on all 10 eRob (s, worst)"),
    ("bringup", "skew_seconds.max", "<=", b.TARGET_SKEW_S, "mode switch skew between slaves (s, worst)"),
    ("bringup", "tick_cpu_us.median", "<=", b.TARGET_TICK_MEDIAN_US,
     "control tick, 14 joints, read+update+write, our CPU (us, median)"),
    ("bringup", "tick_cpu_us.p99", "<=", b.TARGET_TICK_P99_US, "control tick, 14 joints, our CPU (us, p99)"),
    ("bringup", "tick_io_us.median", "<=", math.inf, "control tick: bus I/O, send + receive, both buses (us, median)"),
    ("bringup", "jitter_us.p99", "<=", b.TARGET_JITTER_P99_US, "loop period jitter at 50 Hz (us, p99)"),
    ("khz", "overruns", "<=", b.TARGET_KHZ_OVERRUNS, "1 kHz on the emulated robot for 60 s: overruns"),
    ("khz", "tick_cpu_us.p99", "<=", math.inf, "control tick at 1 kHz, our CPU (us, p99)"),
    *(("dds", f"{rate}_hz.{key}added_tick_us_median", "<=", b.TARGET_DDS_ADDED_TICK_US,
       f"ROS 2 node, {name}: added tick cost at {hz} (us, median)")
      for key, name in (("", "bare DDS"), ("rclpy_", "rclpy (where it imports)"))
      for rate, hz in ((50, "50 Hz"), (1000, "1 kHz"))),
    ("dds", "overruns_with_dds", "<=", 0, "DDS: overruns at 50 Hz and 1 kHz"),
    ("record", "added_tick_us_median", "<=", b.TARGET_RECORD_ADDED_TICK_US,
     "recording: added tick cost (us, median, worst rate)"),
    ("doctor", "seconds.median", "<=", b.TARGET_DOCTOR_S,
     "prime doctor on the healthy virtual Prime: start-up plus checks (s, median)"),
    ("doctor", "seconds.max", "<=", b.TARGET_DOCTOR_S, "prime doctor: start-up plus checks (s, worst run)"),
    ("gate", "added_tick_us_median", "<=", b.TARGET_GATE_ADDED_TICK_US,
     "command gate with collision: added tick at 50 Hz, 14 joints (us, median)"),
    ("gate", "refusing.added_tick_us_median", "<=", math.inf,
     "command gate: added tick while it refuses an arm every tick (us, median)"),
)


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("bench", help=summary("bench"),
                              description="Run the benchmarks and print each figure against its target. "
                                          "Suites: " + "; ".join(f"{k}: {v[2]}" for k, v in SUITES.items()))
    p.add_argument("--only", metavar="SUITE,...", help=f"run only these suites ({', '.join(SUITES)})")
    p.add_argument("--output", metavar="FILE", type=output_file, help="also write every figure as JSON")
    p.add_argument("--json", action="store_true", help="print every figure as JSON instead of the table")
    p.set_defaults(func=run)
    soak = p.add_subparsers(dest="bench_command", metavar="{soak}").add_parser(
        "soak", help="the emulated robot for minutes through all modes, loaded, with faults on both buses",
        description="Run the emulated robot at its control rate through all five modes with a REMOTE stream, both "
                    "cores loaded, and faults injected on both buses in turn (frames lost, delayed and garbled, the "
                    "last slave and the first (the reference clock) lost and returned, a drive fault, an SDO abort, "
                    "a silent Sito, garbage and dropped CAN frames). Reports ticks, overruns, the worst tick, "
                    "jitter, what each fault did against what it should, any fault nobody injected, and that every "
                    "gate was reset and every drive left disabled; exit 1 if any of that fails.")
    soak.add_argument("--minutes", type=real(above=0.0, at_most=LONGEST_S / 60), default=10.0, metavar="M",
                      help="length (default 10)")
    soak.add_argument("--rate", type=real(above=0.0, at_most=2000.0), metavar="HZ",
                      help="control rate (default: update_rate of the controllers file)")
    soak.add_argument("--cpu", type=cpu_number, metavar="N",
                      help="pin the control loop to CPU N, and the emulated robot off it")
    soak.add_argument("--no-load", dest="load", action="store_false", help="leave the cores idle")
    soak.add_argument("--fault-every", type=real(at_least=1.0, at_most=LONGEST_S), default=6.0, metavar="S",
                      help="seconds between injected faults (default 6)")
    soak.add_argument("--dwell", type=real(at_least=1.0, at_most=LONGEST_S), default=10.0, metavar="S",
                      help="seconds in each mode (default 10)")
    soak.add_argument("--faults-once", action="store_true",
                      help="one pass: end once every fault has been injected and has settled (--minutes is then "
                           "the most it may take)")
    soak.add_argument("--output", metavar="FILE", type=output_file, help="also write the figures as JSON")
    soak.add_argument("--json", action="store_true", help="print the figures as JSON instead of the report")
    soak.set_defaults(func=run_soak)


def run_soak(args: argparse.Namespace) -> int:
    from humanoid_prime.bench.soak import bench_soak
    from humanoid_prime.virtual.harness import enter_private_netns

    enter_private_netns()  # re-executes this command in a private network namespace (returns inside)
    console = make_console(stderr=args.json)
    result = bench_soak(args.minutes, rate=args.rate, load=args.load, cpu=args.cpu, fault_every_s=args.fault_every,
                        dwell_s=args.dwell, faults_once=args.faults_once,
                        report=lambda line: console.print(line, markup=False, highlight=False))
    if args.output:
        atomic_write_text(args.output, json.dumps(result, indent=2) + "\n")
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        _print_soak(console, result)
    failures = soak_failures(result)
    for failure in failures:
        console.print(f"[red]soak: {failure}[/red]")
    return 1 if failures else 0


def soak_failures(result: Mapping[str, object]) -> list[str]:
    """What the soak must not show (DESIGN §6), one line each."""
    failures = []
    if result["overruns"]:
        failures.append(f"{result['overruns']} ticks overran (longer than twice the period)")
    failures += [f"{i['fault']} at {i['at_s']:.1f} s: expected {i['expected']}, got {i['outcome']}"
                 for i in members(result["injections"]) if not i["as_designed"]]
    failures += [f"{f['key']} at {f['since_s']:.1f} s, injected by nobody: {f['text']}"
                 for f in members(result["unexpected_faults"])]
    if result["not_injected"]:
        failures.append(f"the pass ended before these faults were injected: {_words(result['not_injected'])}")
    if result["injector_error"]:
        failures.append(f"fault injection stopped: {result['injector_error']}")
    if result["gate_reset_failures"] or result["gates_left_set"]:
        failures.append(f"gates not reset: {result['gate_reset_failures'] or result['gates_left_set']}")
    if result["drives_left_enabled"]:
        failures.append(f"drives left enabled at ring positions {result['drives_left_enabled']}")
    failures += [f"at the end: {p}" for p in _strings(result["problems_at_end"])]
    return failures


def _strings(value: object) -> list[str]:
    return [str(item) for item in value] if isinstance(value, list) else []


def _words(value: object) -> str:
    return ", ".join(_strings(value))


def _print_soak(console: Console, result: Mapping[str, object]) -> None:
    tick, cpu, jitter = member(result, "tick_us"), member(result, "tick_cpu_us"), member(result, "jitter_us")
    console.print(f"{result['ticks']} ticks at {result['update_rate']:g} Hz over {result['minutes']:g} min, load: "
                  f"{result['load'] or 'none'}; overruns (> 2x period): {result['overruns']}; worst tick "
                  f"{result['worst_tick_us']:.0f} us", markup=False)
    console.print(f"tick median {tick['median']:.0f} us p99 {tick['p99']:.0f} us (our CPU {cpu['median']:.0f} / "
                  f"{cpu['p99']:.0f} us); period jitter " + ", ".join(f"{k} {v:.0f} us" for k, v in jitter.items()),
                  markup=False)
    table = Table(title="faults injected", title_justify="left", header_style="bold")
    for column in ("at (s)", "bus", "fault", "expected", "outcome", "flags"):
        table.add_column(column)
    for i in members(result["injections"]):
        outcome = f"[green]{i['outcome']}[/green]" if i["as_designed"] else f"[red]{i['outcome']}[/red]"
        flags = ", ".join(sorted(set(_strings(i["flags"]))))
        table.add_row(f"{i['at_s']:.1f}", str(i["bus"]), str(i["fault"]), str(i["expected"]), outcome, flags)
    console.print(table)
    console.print(f"faults nobody injected: {len(members(result['unexpected_faults']))}; gates left set: "
                  f"{result['gates_left_set'] or 'none'}; drives left enabled: "
                  f"{result['drives_left_enabled'] or 'none'}", markup=False)


def figure(results: Mapping[str, object], suite: str, path: str) -> float | None:
    value = results.get(suite)
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
    results: dict[str, dict[str, object]] = {}
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
    for column in ("target", "measured", "goal", "met", "physical floor"):
        table.add_column(column, justify="left" if column in ("target", "physical floor") else "right")
    for suite, path, op, goal, what in TARGETS:
        if suite not in results:
            continue
        value = figure(results, suite, path)
        note = results[suite].get("skipped") or results[suite].get("error")
        if value is None or not math.isfinite(value):
            table.add_row(what, str(note or "-"), f"{op} {goal:g}", "[yellow]n/a[/yellow]")
            continue
        met = _OPS[op](value, goal)
        floor = ""
        if (suite, path) in FLOORS:
            floor_suite, floor_path, floor_what = FLOORS[suite, path]
            floor_value = figure(results, floor_suite, floor_path)
            floor = f"{floor_value:.4g} ({floor_what})" if floor_value is not None else ""
        goal_text = f"{op} {goal:g}" if math.isfinite(goal) else "-"
        met_text = ("[green]yes[/green]" if met else "[red]no[/red]") if math.isfinite(goal) else ""
        table.add_row(what, f"{value:.4g}", goal_text, met_text, floor)
    console.print(table)
    for suite, data in results.items():
        console.print(f"[bold]{suite}[/bold] {json.dumps(data)}", soft_wrap=True)
    return 0
