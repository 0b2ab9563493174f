"""DDS and recording on the control loop (DESIGN §6): the simulated Prime in STANDBY, paced at 50 Hz and at 1 kHz, once
without ``--dds`` and once with the whole node as ``prime sim --dds`` runs it (joint states, /tf, /clock every
tick, /diagnostics every second), with a subscriber in another process measuring how late each joint state
arrives; then with the publishing attached and detached in turns of half a second: the bare node's, the rclpy
node's where rclpy can be imported (its executor spinning beside the loop), and a tap that publishes nothing (the
hand-off to another thread alone: the floor of any publishing).

Figures: the added tick cost (read + update + write, our CPU): the median tick with publishing attached minus
the median with it detached, in the same run, so a machine whose load drifts weighs on both alike (target
<= 30 us), beside the bare tap's; overruns with and without; joint states published per second against the
loop rate, dropped and late; the latency from the tick to the subscriber (the loop clock is CLOCK_MONOTONIC,
shared by every process on the machine). The physical floor of the latency is a loopback UDP round trip, tens
of us.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from typing import Any

import numpy as np

from humanoid_prime.bench import TARGET_DDS_ADDED_TICK_US, TARGET_RECORD_ADDED_TICK_US
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.robot import load_robot
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.modes import Mode

BENCH_DOMAIN = 231  # away from the usual ROS 2 domains, so a benchmark does not talk to a robot's graph
RATES_HZ = (50.0, 1000.0)
TURN_S = 0.5  # publishing attached, then detached, for this long each, through a paired run


class _Nothing:
    """A tap consumer that publishes nothing: what handing each tick over costs by itself."""

    def on_tick(self, sample: Any) -> None: ...
    def on_mode(self, message: Any) -> None: ...
    def on_safety(self, message: Any) -> None: ...
    def on_remote(self, message: Any) -> None: ...


def _run(robot, config, rate: float, seconds: float, dds: bool, record: str | None = None,
         tap_only: bool = False, paired: bool = False, backend: str = "dds") -> dict[str, Any]:
    from humanoid_prime.sim.demo import START_POSE, build_simulation

    _, manager = build_simulation(robot, config, initial_pose=START_POSE, update_rate=rate, clock=time.monotonic)
    listener = bridge = recorder = tap = None
    result: dict[str, Any] = {"rate_hz": rate, "dds": dds, "record": record is not None, "tap_only": tap_only,
                              "paired": paired, "backend": backend if dds else None}
    with manager:
        manager.start()
        manager.request_mode(Mode.STANDBY)
        if dds:
            if not paired:  # the paired run measures the tick alone
                listener = subprocess.Popen([sys.executable, "-m", "humanoid_prime.bench.dds", str(BENCH_DOMAIN)],
                                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            # Stamps in the loop clock (CLOCK_MONOTONIC); /clock on, as in simulation.
            if backend == "rclpy":  # the whole rclpy node, as `prime sim --dds --ros-backend rclpy` has it
                from humanoid_prime.dds.rclpy_node import rclpy_bridge

                bridge = rclpy_bridge(manager, domain=BENCH_DOMAIN, sim_clock=True)
            else:
                from humanoid_prime.dds.bridge import bridge_manager

                bridge = bridge_manager(manager, domain=BENCH_DOMAIN, sim_clock=True)
            deadline = time.monotonic() + 30.0
            while listener is not None and not bridge.joint_state_readers() and time.monotonic() < deadline:
                time.sleep(0.01)
        if record is not None:
            from humanoid_prime.record.mcap import Recorder

            recorder = Recorder(record, manager)
        if tap_only:
            from humanoid_prime.control.tap import TickTap

            tap = TickTap(manager, _Nothing(), name="bench-tap")
        began = time.monotonic()
        if paired:
            result["paired_us"] = _paired(manager, seconds, bridge, tap)
        else:
            manager.run(duration=seconds)
        wall = time.monotonic() - began
        stats = manager.stats.summary()
        if tap is not None:
            tap.close()
        if bridge is not None and not paired:
            bridge.close()
            result["bridge"] = bridge.summary()
            published = result["bridge"]["topics"]["/prime/joint_states"]["published"]
            result["published_per_s"] = round(published / wall, 1)
        elif bridge is not None:
            bridge.close()
        if recorder is not None:
            recorder.close()
            result["recorder"] = recorder.summary()
    if listener is not None:
        out, _ = listener.communicate("", timeout=60)
        result["subscriber"] = json.loads(out or "{}")
    result.update(ticks=stats["ticks"], overruns=stats["overruns"], tick_us=stats["tick_us"],
                  jitter_us=stats["jitter_us"])
    return result


def _paired(manager: ControllerManager, seconds: float, bridge: Any, tap: Any) -> dict[str, float]:
    """Run ``seconds`` in turns of TURN_S with the bridge's (or the bare tap's) hand-off attached, then detached;
    the median tick of each (each turn's first tick aside), and what attaching adds. Both start attached."""
    from humanoid_prime.control.tap import TickTap

    turns: dict[bool, list[np.ndarray]] = {True: [], False: []}
    count = max(2, round(seconds / TURN_S))
    for turn in range(count):
        attached = turn % 2 == 0
        if turn and bridge is not None:
            if attached:
                bridge.resume()
            else:
                bridge.pause()
        elif turn:
            if attached:
                tap = TickTap(manager, _Nothing(), name="bench-tap")
            else:
                tap.close()
        first = manager.stats.ticks
        manager.run(duration=seconds / count)
        turns[attached].append(manager.stats.costs[np.arange(first + 1, manager.stats.ticks) % manager.stats.capacity])
    if tap is not None:
        tap.close()
    on_us, off_us = (float(np.median(np.concatenate(turns[state]))) * 1e6 for state in (True, False))
    return {"attached": round(on_us, 1), "detached": round(off_us, 1), "added": round(on_us - off_us, 1)}


def _added(plain: dict[str, Any], run: dict[str, Any]) -> float | None:
    """What ``run`` adds to the median tick of ``plain``."""
    if plain["tick_us"]["median"] is None or run["tick_us"]["median"] is None:
        return None
    return round(run["tick_us"]["median"] - plain["tick_us"]["median"], 1)


def bench_dds(seconds: float = 10.0) -> dict[str, Any]:
    robot = load_robot(use_sim=True)
    config = load_controllers(robot.names)
    results: dict[str, Any] = {"seconds": seconds, "target_added_tick_us": TARGET_DDS_ADDED_TICK_US}
    import importlib.util

    rclpy = importlib.util.find_spec("rclpy") is not None
    for rate in RATES_HZ:
        plain = _run(robot, config, rate, seconds, dds=False)
        bridged = _run(robot, config, rate, seconds, dds=True)
        paired = _run(robot, config, rate, seconds, dds=True, paired=True)
        tapped = _run(robot, config, rate, seconds, dds=False, tap_only=True, paired=True)
        results[f"{rate:g}_hz"] = {"without": plain, "with": bridged, "paired": paired, "tap_paired": tapped,
                                   "added_tick_us_median": paired["paired_us"]["added"],
                                   "tap_added_tick_us_median": tapped["paired_us"]["added"],
                                   "across_runs_added_tick_us_median": _added(plain, bridged)}
        if rclpy:  # the rclpy node in the same run, beside the bare one and the floor: its hand-off paired, and
            # the whole node (its executor threads too) against the run without it
            rclpy_paired = _run(robot, config, rate, seconds, dds=True, paired=True, backend="rclpy")
            rclpy_run = _run(robot, config, rate, seconds, dds=True, backend="rclpy")
            results[f"{rate:g}_hz"].update(rclpy_paired=rclpy_paired, rclpy_with=rclpy_run,
                                           rclpy_added_tick_us_median=rclpy_paired["paired_us"]["added"],
                                           rclpy_across_runs_added_tick_us_median=_added(plain, rclpy_run))
    results["added_tick_us_median"] = max(results[f"{rate:g}_hz"]["added_tick_us_median"] for rate in RATES_HZ)
    results["rclpy"] = "measured" if rclpy else "rclpy cannot be imported here: only the bare backend measured"
    if rclpy:
        results["rclpy_added_tick_us_median"] = max(results[f"{rate:g}_hz"]["rclpy_added_tick_us_median"]
                                                    for rate in RATES_HZ)
    results["floors"] = {"tap_added_tick_us_median": max(results[f"{rate:g}_hz"]["tap_added_tick_us_median"]
                                                         for rate in RATES_HZ)}
    results["overruns_with_dds"] = sum(results[f"{rate:g}_hz"]["with"]["overruns"] for rate in RATES_HZ)
    return results


def listen(domain: int) -> dict[str, Any]:
    """Read /prime/joint_states until stdin closes; each sample's arrival minus its stamp (same clock)."""
    import threading

    from cyclonedds.internal import InvalidSample
    from cyclonedds.util import duration

    from humanoid_prime.dds import messages as msg
    from humanoid_prime.dds.node import DdsNode

    latencies: list[float] = []
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    with DdsNode(domain) as node:
        reader = node.reader("/prime/joint_states", msg.JointState, depth=1000)
        while not done.is_set():  # take_iter wakes on each arrival (a wait set), not on a polling period
            for sample in reader.take_iter(timeout=duration(milliseconds=100)):
                if not isinstance(sample, InvalidSample):
                    latencies.append(time.monotonic() - msg.seconds(sample.header.stamp))
                if done.is_set():
                    break
    values = np.array(latencies) * 1e6
    return {"received": len(latencies),
            "latency_us": {"median": float(np.median(values)) if values.size else None,
                           "p99": float(np.percentile(values, 99)) if values.size else None}}


def bench_record(seconds: float = 10.0) -> dict[str, Any]:
    """--record on the loop: the simulated Prime in STANDBY at 50 Hz and 1 kHz, without and with a recorder."""
    import tempfile
    from pathlib import Path

    robot = load_robot(use_sim=True)
    config = load_controllers(robot.names)
    results: dict[str, Any] = {"seconds": seconds, "target_added_tick_us": TARGET_RECORD_ADDED_TICK_US}
    with tempfile.TemporaryDirectory() as folder:
        for rate in RATES_HZ:
            plain = _run(robot, config, rate, seconds, dds=False)
            recorded = _run(robot, config, rate, seconds, dds=False, record=str(Path(folder) / f"{rate:g}.mcap"))
            added = round(recorded["tick_us"]["median"] - plain["tick_us"]["median"], 1)
            results[f"{rate:g}_hz"] = {"without": plain, "with": recorded, "added_tick_us_median": added}
    results["added_tick_us_median"] = max(results[f"{rate:g}_hz"]["added_tick_us_median"] for rate in RATES_HZ)
    results["dropped_ticks"] = sum(results[f"{rate:g}_hz"]["with"]["recorder"]["dropped_ticks"] for rate in RATES_HZ)
    return results


if __name__ == "__main__":
    print(json.dumps(listen(int(sys.argv[1]))))
