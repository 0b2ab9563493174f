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
of us. Recording is measured the same way: the recorder attached and detached in turns of one run (target
<= 20 us), beside the difference between a run without it and one with it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from typing import TYPE_CHECKING, TypedDict

import numpy as np
import numpy.typing as npt

from humanoid_prime.bench import TARGET_DDS_ADDED_TICK_US, TARGET_RECORD_ADDED_TICK_US
from humanoid_prime.config.controllers import ControllersConfig, load_controllers
from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.tap import TickSample, TickTap
from humanoid_prime.control.topics import ControlMode, MitCommand, SafetyStatus
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode

if TYPE_CHECKING:  # the nodes and the recorder are imported by the runs that use them
    from humanoid_prime.dds.bridge import DdsBridge
    from humanoid_prime.dds.rclpy_node import RclpyBridge
    from humanoid_prime.record.mcap import Recorder, RecordSummary

BENCH_DOMAIN = 231  # away from the usual ROS 2 domains, so a benchmark does not talk to a robot's graph
RATES_HZ = (50.0, 1000.0)
TURN_S = 0.5  # publishing attached, then detached, for this long each, through a paired run


class _Nothing:
    """A tap consumer that publishes nothing: what handing each tick over costs by itself."""

    def on_tick(self, sample: TickSample) -> None: ...
    def on_mode(self, message: ControlMode) -> None: ...
    def on_safety(self, message: SafetyStatus) -> None: ...
    def on_remote(self, message: MitCommand) -> None: ...


class Paired(TypedDict):
    """The median tick (us) with the hand-off attached and detached in turns, and what attaching adds."""

    attached: float
    detached: float
    added: float


class Run(TypedDict, total=False):
    """One run of the simulated Prime: how it was set up, what it published or recorded, and its ticks."""

    rate_hz: float
    dds: bool
    record: bool
    tap_only: bool
    paired: bool
    backend: str | None
    paired_us: Paired  # a paired run's
    bridge: dict[str, object]  # the node's own summary, with --dds
    published_per_s: float
    recorder: RecordSummary  # with --record
    subscriber: dict[str, object]  # what the listener in another process received (``listen``)
    ticks: int
    overruns: int
    tick_us: dict[str, float | None]  # median, p99, max
    jitter_us: object  # as the loop's statistics give it


def _run(robot: Robot, config: ControllersConfig, rate: float, seconds: float, dds: bool, record: str | None = None,
         tap_only: bool = False, paired: bool = False, backend: str = "dds") -> Run:
    from humanoid_prime.sim.demo import START_POSE, build_simulation

    _, manager = build_simulation(robot, config, initial_pose=START_POSE, update_rate=rate, clock=time.monotonic)
    listener: subprocess.Popen[str] | None = None
    bridge: DdsBridge | RclpyBridge | None = None
    recorder: Recorder | None = None
    tap: TickTap | None = None
    result: Run = {"rate_hz": rate, "dds": dds, "record": record is not None, "tap_only": tap_only,
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
            tap = TickTap(manager, _Nothing(), name="bench-tap")
        began = time.monotonic()
        if paired:
            result["paired_us"] = _paired(manager, seconds, bridge, tap, recorder)
        else:
            manager.run(duration=seconds)
        wall = time.monotonic() - began
        stats = manager.stats
        ticks, overruns, tick_us, jitter_us = stats.ticks, stats.overruns, stats.tick_us(), stats.summary()["jitter_us"]
        if tap is not None:
            tap.close()
        if bridge is not None and not paired:
            bridge.close()
            result["bridge"] = bridge.summary()
            result["published_per_s"] = round(bridge.counts["/prime/joint_states"].samples / wall, 1)
        elif bridge is not None:
            bridge.close()
        if recorder is not None:
            recorder.close()
            result["recorder"] = recorder.summary()
    if listener is not None:
        out, _ = listener.communicate("", timeout=60)
        result["subscriber"] = json.loads(out or "{}")
    result.update({"ticks": ticks, "overruns": overruns, "tick_us": tick_us, "jitter_us": jitter_us})
    return result


def _paired(manager: ControllerManager, seconds: float, bridge: DdsBridge | RclpyBridge | None,
            tap: TickTap | None, recorder: Recorder | None = None) -> Paired:
    """Run ``seconds`` in turns of TURN_S with the bridge's (or the recorder's, or the bare tap's) hand-off attached,
    then detached; the median tick of each (each turn's first tick aside), and what attaching adds. Each starts
    attached."""
    turns: dict[bool, list[npt.NDArray[np.float64]]] = {True: [], False: []}
    count = max(2, round(seconds / TURN_S))
    for turn in range(count):
        attached = turn % 2 == 0
        if turn and bridge is not None:
            if attached:
                bridge.resume()
            else:
                bridge.pause()
        elif turn and recorder is not None:
            if attached:
                recorder.attach(manager)
            else:
                recorder.detach()
        elif turn:
            if attached:
                tap = TickTap(manager, _Nothing(), name="bench-tap")
            elif tap is not None:
                tap.close()
        first = manager.stats.ticks
        manager.run(duration=seconds / count)
        turns[attached].append(manager.stats.costs[np.arange(first + 1, manager.stats.ticks) % manager.stats.capacity])
    if tap is not None:
        tap.close()
    on_us, off_us = (float(np.median(np.concatenate(turns[state]))) * 1e6 for state in (True, False))
    return {"attached": round(on_us, 1), "detached": round(off_us, 1), "added": round(on_us - off_us, 1)}


def _added(plain: Run, run: Run) -> float | None:
    """What ``run`` adds to the median tick of ``plain``."""
    before, after = plain["tick_us"]["median"], run["tick_us"]["median"]
    if before is None or after is None:
        return None
    return round(after - before, 1)


def bench_dds(seconds: float = 10.0) -> dict[str, object]:
    robot = load_robot(use_sim=True)
    config = load_controllers(robot.names)
    results: dict[str, object] = {"seconds": seconds, "target_added_tick_us": TARGET_DDS_ADDED_TICK_US}
    import importlib.util

    rclpy = importlib.util.find_spec("rclpy") is not None
    added: list[float] = []  # by rate: the bare node's, the tap's, the rclpy node's hand-off
    tap_added: list[float] = []
    rclpy_added: list[float] = []
    overruns = 0  # with the bare node
    for rate in RATES_HZ:
        plain = _run(robot, config, rate, seconds, dds=False)
        bridged = _run(robot, config, rate, seconds, dds=True)
        paired = _run(robot, config, rate, seconds, dds=True, paired=True)
        tapped = _run(robot, config, rate, seconds, dds=False, tap_only=True, paired=True)
        added.append(paired["paired_us"]["added"])
        tap_added.append(tapped["paired_us"]["added"])
        overruns += bridged["overruns"]
        at_rate: dict[str, object] = {"without": plain, "with": bridged, "paired": paired, "tap_paired": tapped,
                                      "added_tick_us_median": added[-1], "tap_added_tick_us_median": tap_added[-1],
                                      "across_runs_added_tick_us_median": _added(plain, bridged)}
        if rclpy:  # the rclpy node in the same run, beside the bare one and the floor: its hand-off paired, and
            # the whole node (its executor threads too) against the run without it
            rclpy_paired = _run(robot, config, rate, seconds, dds=True, paired=True, backend="rclpy")
            rclpy_run = _run(robot, config, rate, seconds, dds=True, backend="rclpy")
            rclpy_added.append(rclpy_paired["paired_us"]["added"])
            at_rate.update(rclpy_paired=rclpy_paired, rclpy_with=rclpy_run,
                           rclpy_added_tick_us_median=rclpy_added[-1],
                           rclpy_across_runs_added_tick_us_median=_added(plain, rclpy_run))
        results[f"{rate:g}_hz"] = at_rate
    results["added_tick_us_median"] = max(added)
    results["rclpy"] = "measured" if rclpy else "rclpy cannot be imported here: only the bare backend measured"
    if rclpy:
        results["rclpy_added_tick_us_median"] = max(rclpy_added)
    results["floors"] = {"tap_added_tick_us_median": max(tap_added)}
    results["overruns_with_dds"] = overruns
    return results


def listen(domain: int) -> dict[str, object]:
    """Read /prime/joint_states until stdin closes; each sample's arrival minus its stamp (same clock)."""
    import threading

    from cyclonedds.internal import InvalidSample
    from cyclonedds.util import duration

    from humanoid_prime.dds import messages as msg
    from humanoid_prime.dds.node import DdsNode

    latencies: list[float] = []
    done = threading.Event()

    def wait_for_stdin() -> None:
        sys.stdin.read()
        done.set()

    threading.Thread(target=wait_for_stdin, daemon=True).start()
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


def bench_record(seconds: float = 10.0) -> dict[str, object]:
    """--record on the loop: the simulated Prime in STANDBY at 50 Hz and 1 kHz, without and with a recorder."""
    import tempfile
    from pathlib import Path

    robot = load_robot(use_sim=True)
    config = load_controllers(robot.names)
    results: dict[str, object] = {"seconds": seconds, "target_added_tick_us": TARGET_RECORD_ADDED_TICK_US}
    added: list[float] = []
    dropped = 0
    with tempfile.TemporaryDirectory() as folder:
        for rate in RATES_HZ:  # the recorder attached and detached in turns of one run (two runs differ by more)
            plain = _run(robot, config, rate, seconds, dds=False)
            recorded = _run(robot, config, rate, seconds, dds=False, record=str(Path(folder) / f"{rate:g}.mcap"))
            paired = _run(robot, config, rate, seconds, dds=False, record=str(Path(folder) / f"{rate:g}-turns.mcap"),
                          paired=True)
            added.append(paired["paired_us"]["added"])
            dropped += recorded["recorder"]["dropped_ticks"]
            results[f"{rate:g}_hz"] = {"without": plain, "with": recorded, "paired": paired,
                                       "added_tick_us_median": added[-1],
                                       "across_runs_added_tick_us_median": _added(plain, recorded)}
    results["added_tick_us_median"] = max(round(value, 1) for value in added)
    results["dropped_ticks"] = dropped
    return results


def _ticked(run: Run) -> float:
    """The median tick (us) of a run that ticked."""
    median = run["tick_us"]["median"]
    if median is None:
        raise PrimeError(f"the run at {run['rate_hz']:g} Hz made no tick")
    return median


if __name__ == "__main__":
    print(json.dumps(listen(int(sys.argv[1]))))
