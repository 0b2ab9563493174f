"""EtherCAT figures (DESIGN §6) on the emulated ring: cold bring-up, per-cycle cost, SDO gain switches.

- Cold bring-up of the ten eRob to OP with joint states flowing (configure + activate + first read), once
  with a bring-up loop at 50 Hz (the ROS 2 original's pacing) and once at 1 kHz (``bringup_rate``).
- Per-cycle cost of ``EthercatSystem.read()`` + ``write()`` at the control rate (the wait for the next
  period excluded), idle and while gain switches run over SDO; wall time, and the loop thread's own CPU
  time (on a small machine the emulator process competes for the same cores); and back to back, where
  the caches stay warm (after a 20 ms idle period this VM runs the same code several times slower).
- Gain switches: two registers on every slave, written one worker per slave (parallel, the workers meeting
  before their last write as the impedance manager's do) and from one thread (sequential), with wall time
  and the spread of the slaves' finishing times (skew).
"""

from __future__ import annotations

import json
import statistics
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from humanoid_prime.bench import TARGET_BRINGUP_S, TARGET_SKEW_S, TARGET_SWITCH_S
from humanoid_prime.config.calibration import load_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.erob.objects import BUS_GAIN_GATE, POS_LOOP_GAIN, VEL_LOOP_GAIN
from humanoid_prime.drivers.ethercat.sdo_client import SizedSdo
from humanoid_prime.drivers.ethercat.soem_master import SoemMaster
from humanoid_prime.drivers.ethercat.system import EthercatSystem
from humanoid_prime.runtime.impedance import Rendezvous
from humanoid_prime.virtual.netns import EmulatedRing, netns_unavailable_reason

# Two register sets a switch alternates between (pos_reg, vel_reg): STANDBY-like and DAMPING-like.
SWITCH_REGISTERS = ((515, 19), (0, 56))


def _percentiles(samples_us: list[float]) -> dict[str, float | int]:
    if not samples_us:
        return {"n": 0}
    return {"n": len(samples_us), "median": round(statistics.median(samples_us), 1),
            "p99": round(float(np.percentile(samples_us, 99)), 1), "max": round(max(samples_us), 1)}


class _Loop:
    """The controller manager's cycle in a thread: read() + write() every period, cost of each recorded."""

    def __init__(self, system: EthercatSystem, robot: Robot, rate_hz: float) -> None:
        self.system = system
        self.period = 1.0 / rate_hz
        self.command = CommandArrays(robot.n)
        self.state = StateArrays(robot.n)
        self.costs_us: list[float] = []
        self.cpu_us: list[float] = []  # this thread's CPU time: the cost without preemption by the emulator
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-ethercat-loop", daemon=True)

    def _run(self) -> None:
        rate = Rate(1.0 / self.period, sleep=self._stop.wait)
        while not self._stop.is_set():
            rate.wait()
            start, cpu = time.perf_counter_ns(), time.thread_time_ns()
            self.system.read(0.0, self.state)
            self.system.write(0.0, self.command)
            self.costs_us.append((time.perf_counter_ns() - start) / 1e3)
            self.cpu_us.append((time.thread_time_ns() - cpu) / 1e3)

    def __enter__(self) -> _Loop:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def _switches(master: SoemMaster, positions: list[int], count: int, parallel: bool) -> dict[str, Any]:
    """Alternate the two register sets ``count`` times; wall time and skew per switch."""
    walls, skews = [], []
    objects = SizedSdo(master)
    for position in positions:  # each register's size, learnt before the clock starts
        objects.size(position, POS_LOOP_GAIN)
        objects.size(position, VEL_LOOP_GAIN)

    def write(position: int, registers: tuple[int, int], start: float, rendezvous: Rendezvous) -> float:
        objects.write(position, POS_LOOP_GAIN, registers[0])
        rendezvous.meet()
        objects.write(position, VEL_LOOP_GAIN, registers[1])
        return time.monotonic() - start

    alone = Rendezvous(1)
    with ThreadPoolExecutor(max_workers=len(positions)) as pool:
        for k in range(count):
            registers = SWITCH_REGISTERS[k % 2]
            start = time.monotonic()
            if parallel:
                rendezvous = Rendezvous(len(positions))
                done = list(pool.map(lambda p, r=registers, s=start, m=rendezvous: write(p, r, s, m), positions))
            else:
                done = [write(p, registers, start, alone) for p in positions]
            walls.append(max(done))
            skews.append(max(done) - min(done))
    return {"switches": count, "writes_per_switch": 2 * len(positions),
            "wall_ms": _percentiles([w * 1e3 for w in walls]), "skew_ms": _percentiles([s * 1e3 for s in skews]),
            "meets_target": max(walls) <= TARGET_SWITCH_S and max(skews) <= TARGET_SKEW_S}


def bench_ethercat(*, bringup_rates_hz: tuple[float, ...] = (50.0, 1000.0), cycles: int = 250,
                   switches: int = 20, hardware_file: str | Path | None = None,
                   controllers_file: str | Path | None = None) -> dict[str, Any]:
    """Measure on the emulated ring; ``{"skipped": reason}`` where no network namespace can be made."""
    reason = netns_unavailable_reason()
    if reason is not None:
        return {"skipped": reason}
    robot = load_robot(hardware_file)
    controllers = load_controllers(robot.names, controllers_file)
    calibration = load_calibration(robot.hardware)
    update_rate = controllers.update_rate
    positions = sorted(robot.hardware.erob_slaves.values())
    report: dict[str, Any] = {"update_rate": update_rate, "slaves": len(positions),
                              "target_bringup_s": TARGET_BRINGUP_S, "bringup": {}}
    for rate in bringup_rates_hz:
        with EmulatedRing(slaves=len(positions)) as ring:
            master = SoemMaster(ring.master_interface, update_rate=update_rate, bringup_rate=rate)
            system = EthercatSystem(robot, calibration, update_rate=update_rate, bringup_rate=rate,
                                    master=master)
            try:
                start = time.monotonic()
                system.configure()
                system.activate()
                system.read(0.0, StateArrays(robot.n))
                cold = time.monotonic() - start
                assert system.bringup is not None
                report["bringup"][f"{rate:g}_hz"] = {
                    "seconds": round(cold, 3), "op_seconds": round(system.bringup.seconds, 3),
                    "bringup_cycles": system.bringup.cycles, "meets_target": cold <= TARGET_BRINGUP_S}
                if rate == max(bringup_rates_hz):
                    report.update(_steady_state(system, master, robot, update_rate, positions, cycles, switches))
            finally:
                system.shutdown()
    return report


def _hot_cycles(system: EthercatSystem, robot: Robot, cycles: int) -> list[float]:
    """read() + write() back to back: the code's cost with warm caches (each read waits for the frame the
    previous write sent, so the ring's turnaround is included)."""
    command, state = CommandArrays(robot.n), StateArrays(robot.n)
    costs = []
    for _ in range(cycles):
        start = time.perf_counter_ns()
        system.read(0.0, state)
        system.write(0.0, command)
        costs.append((time.perf_counter_ns() - start) / 1e3)
    return costs


def _steady_state(system: EthercatSystem, master: SoemMaster, robot: Robot, update_rate: float,
                  positions: list[int], cycles: int, switches: int) -> dict[str, Any]:
    hot = _hot_cycles(system, robot, cycles)
    with _Loop(system, robot, update_rate) as loop:
        deadline = time.monotonic() + cycles / update_rate * 2 + 1.0
        while len(loop.costs_us) < cycles and time.monotonic() < deadline:
            time.sleep(0.05)
        idle, idle_cpu = list(loop.costs_us), list(loop.cpu_us)
        objects = SizedSdo(master)
        for position in positions:
            objects.write(position, BUS_GAIN_GATE, 1)
        mark = len(loop.costs_us)
        parallel = _switches(master, positions, switches, parallel=True)
        sequential = _switches(master, positions, switches, parallel=False)
        during = loop.costs_us[mark:]
        for position in positions:
            objects.write(position, BUS_GAIN_GATE, 0)
    return {
        "cycle_us": _percentiles(idle[5:]),
        "cycle_cpu_us": _percentiles(idle_cpu[5:]),
        "cycle_us_back_to_back": _percentiles(hot[5:]),
        "cycle_us_during_sdo": _percentiles(during),
        "sdo_switch_parallel": parallel,
        "sdo_switch_sequential": sequential,
        "sdo_frames_repeated": master.lost_frames,
        "wkc_errors": system.wkc_errors,
        "flags_at_end": dict(system.flags),
    }


if __name__ == "__main__":
    print(json.dumps(bench_ethercat(), indent=2))
