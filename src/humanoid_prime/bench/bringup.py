"""Whole-robot figures on the virtual Prime (DESIGN §6): cold bring-up of 10 eRob + 4 Sito with joint states
flowing, eRob gains applied on a mode switch (wall time and per-slave skew), and the 50 Hz control tick
and period jitter for all 14 joints.

It runs ``prime bringup --emulate`` as a separate process (the emulation lives in a private network
namespace of its own) with a DAMPING <-> STANDBY sequence, and reads the run's summary.

The bring-up figure is the stack's: from the command's start to the first joint states, less the stage that
starts the emulated robot itself (its process importing MuJoCo and loading the model, the veth pair), which on
the robot is the power switch, long before anyone types the command. That stage is reported beside it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from humanoid_prime.bench.floors import can_frame_s, ethercat_cycle_s
from humanoid_prime.drivers.ethercat.master import RX_DTYPE, TX_DTYPE
from humanoid_prime.drivers.sito.bus import FRAMES_PER_WRIST, bus_cycle
from humanoid_prime.errors import PrimeError
from humanoid_prime.virtual.harness import EMULATOR_STAGE

SEQUENCE = "DAMPING,STANDBY,DAMPING,STANDBY,DAMPING,STANDBY,DAMPING"


def bench_bringup(dwell: float = 2.0, *, sequential: bool = False, timeout: float = 180.0) -> dict[str, Any]:
    options = ["--sequence", SEQUENCE, "--dwell", str(dwell), *(["--sequential-sdo"] if sequential else [])]
    return bringup_figures(emulated_bringup(options, timeout=timeout), sequential=sequential)


def emulated_bringup(options: list[str], *, timeout: float) -> dict[str, Any]:
    """Run ``prime bringup --emulate`` with ``options`` in a process of its own and return its summary."""
    with tempfile.TemporaryDirectory(prefix="prime-bench-") as tmp:
        summary_path = Path(tmp) / "summary.json"
        command = [sys.executable, "-m", "humanoid_prime", "bringup", "--emulate", "--no-live", *options,
                   "--summary", str(summary_path), "--socket", str(Path(tmp) / "control.sock")]
        proc = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
        if not summary_path.exists():  # a faulted run still reports its figures, with its problems
            last = (proc.stderr.strip() or proc.stdout.strip()).splitlines()
            raise PrimeError(f"emulated bringup {' '.join(options)} failed (exit {proc.returncode}): "
                             f"{last[-1] if last else 'no output'}")
        return json.loads(summary_path.read_text())


def bringup_figures(summary: dict[str, Any], *, sequential: bool = False) -> dict[str, Any]:
    """The benchmark's figures from the summary of an emulated ``prime bringup`` run."""
    switches = [s for s in summary["mode_switches"] if s["mode"] in ("DAMPING", "STANDBY")]
    walls = np.array([s["wall_seconds"] for s in switches]) if switches else np.array([np.nan])
    skews = np.array([s["skew_seconds"] for s in switches]) if switches else np.array([np.nan])
    slaves, wrists = summary["end"]["slaves"], summary["end"]["sito"]  # as the hardware file has them
    period_s = 1.0 / summary["update_rate"]
    can_frames = FRAMES_PER_WRIST * wrists  # per bus cycle: a command to each wrist, its 0xB1 and 0xB2 feedback
    emulator_start = sum(stage["seconds"] for stage in summary["stages"] if stage["name"] == EMULATOR_STAGE)
    return {
        "bringup_seconds": summary["bringup_seconds"] - emulator_start,
        "emulator_start_seconds": emulator_start,
        "ethercat_bringup": summary["ethercat_bringup"],
        "ok": summary["ok"],
        "problems": summary["problems"],
        "end": summary["end"],
        "switches": len(switches),
        "switch_seconds": {"median": float(np.median(walls)), "max": float(np.max(walls))},
        "skew_seconds": {"median": float(np.median(skews)), "max": float(np.max(skews))},
        "tick_us": summary["tick_us"],
        "tick_cpu_us": summary["tick_cpu_us"],
        "tick_io_us": summary["tick_io_us"],
        "floors": {
            "ethercat_cycle_us": round(ethercat_cycle_s(slaves, RX_DTYPE.itemsize, TX_DTYPE.itemsize) * 1e6, 1),
            "can_cycle_us": [round(can_frames * can_frame_s() * 1e6, 1),
                             round(can_frames * can_frame_s(worst_stuffing=True) * 1e6, 1)],
            "can_load_percent_every_tick_at_1khz": round(can_frames * can_frame_s() / 1e-3 * 100, 1),
            "sito_ticks_per_bus_cycle_at_1khz": bus_cycle(1000.0, wrists, 1e6)[0],
            "period_us": round(period_s * 1e6, 1),
        },
        "jitter_us": summary["jitter_us"],
        "ticks": summary["ticks"],
        "overruns": summary["overruns"],
        "faults": summary["faults"],
        "parallel_sdo": not sequential,
    }
