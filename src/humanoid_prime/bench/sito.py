"""Sito wrists (DESIGN §6): ``SitoSystem.read() + write()`` cost for the four motors and the bus load at 50 Hz.

The run is put together as every run is (``runtime.session.assemble``: the registry's wrists component under one
controller manager, started in stages); the measured calls are the component's own. The emulated wrists answer on
a virtual bus in this process (a background thread at the 1 kHz firmware
rate, so their work competes with the measured calls as it would not on the robot). The cost is reported
paced at 50 Hz, as the control loop calls it (each call starts with caches cooled by the 20 ms wait), and
back to back (warm). A sniffer on the same channel records every frame; the load is each frame's exact
bit count (stuff bits, CRC, delimiters, ACK, EOF and intermission included) over 1 Mbit/s. The target
applies to the host's traffic; the feedback the wrists stream at the control period is reported beside it.
"""

from __future__ import annotations

import math
import time
import uuid

import can
import numpy as np

from humanoid_prime.bench import TARGET_LOAD_PERCENT
from humanoid_prime.config.calibration import identity_calibration
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.description import SITO_BLOCK
from humanoid_prime.config.robot import load_robot
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.sito.bus import frame_bits
from humanoid_prime.drivers.sito.protocol import HOST_FRAME_TYPES
from humanoid_prime.drivers.sito.system import SitoSystem
from humanoid_prime.runtime.registry import ComponentSettings
from humanoid_prime.runtime.session import assemble
from humanoid_prime.virtual.plant import InertiaPlant
from humanoid_prime.virtual.sito import SitoEmulator

UPDATE_RATE = 50.0
WARM_TICKS = 2000
_HOST_TYPES = frozenset(int(t) for t in HOST_FRAME_TYPES)


def _percentiles(samples_ns: list[int]) -> dict[str, float]:
    values = np.array(samples_ns) / 1000.0
    return {"median": float(np.median(values)), "p99": float(np.percentile(values, 99))}


def bench_sito(seconds: float = 2.0) -> dict[str, object]:
    """Run the four emulated wrists for ``seconds`` at 50 Hz and report tick cost and bus load."""
    robot = load_robot()
    bitrate = robot.hardware.can.bitrate
    channel = f"sito-bench-{uuid.uuid4().hex}"
    buses = [can.Bus(interface="virtual", channel=channel) for _ in range(2)]
    emulator_bus, sniffer = buses
    plant = InertiaPlant.wrists(len(robot.hardware.sito_joints), gravity=0.3, coulomb=0.02)
    emulator = SitoEmulator.for_robot(robot, emulator_bus, plant)
    settings = ComponentSettings(robot, identity_calibration(robot.hardware), update_rate=UPDATE_RATE,
                                 can_interface="virtual", can_channel=channel, emulated=True)
    manager = assemble(settings, load_controllers(robot.names), (SITO_BLOCK,), broadcaster_only=True)
    system = manager.resources.components[0]
    assert isinstance(system, SitoSystem)  # the registry builds the wrists as a SitoSystem
    command, state = CommandArrays(robot.n), StateArrays(robot.n)
    idx = system.indices
    command.stiffness[idx] = 20.0
    command.damping[idx] = 2.0
    period = 1.0 / UPDATE_RATE
    paced: list[int] = []
    warm: list[int] = []
    try:
        emulator.start()
        manager.start()
        while sniffer.recv(0.0) is not None:  # activation traffic is not steady state
            pass
        start = time.monotonic()
        ticks = round(seconds * UPDATE_RATE)
        rate = Rate(UPDATE_RATE)
        for k in range(ticks):
            rate.wait()
            t = k * period
            command.position[idx] = 0.2 * math.sin(math.pi * t)
            command.velocity[idx] = 0.2 * math.pi * math.cos(math.pi * t)
            begin = time.perf_counter_ns()
            system.read(t, state)
            system.write(t, command)
            paced.append(time.perf_counter_ns() - begin)
        wall = time.monotonic() - start
        host_bits = feedback_bits = host_frames = feedback_frames = 0
        while (msg := sniffer.recv(0.0)) is not None:
            if msg.is_error_frame:
                continue
            if msg.arbitration_id & 0xFF in _HOST_TYPES:
                host_bits += frame_bits(msg)
                host_frames += 1
            else:
                feedback_bits += frame_bits(msg)
                feedback_frames += 1
        flags = dict(system.flags)

        for _ in range(WARM_TICKS):  # back to back: the cost with warm caches
            begin = time.perf_counter_ns()
            system.read(0.0, state)
            system.write(0.0, command)
            warm.append(time.perf_counter_ns() - begin)
    finally:
        manager.shutdown()
        emulator.stop()
        for bus in buses:
            bus.shutdown()

    host_seconds = ticks / UPDATE_RATE  # host traffic is per tick: normalise to exactly 50 Hz
    host_load = 100.0 * host_bits / host_seconds / bitrate
    feedback_load = 100.0 * feedback_bits / wall / bitrate
    return {
        "motors": len(system.can_ids),
        "update_rate": UPDATE_RATE,
        "ticks": ticks,
        "read_write_us": _percentiles(paced),
        "read_write_warm_us": _percentiles(warm),
        "host_frames_per_s": host_frames / host_seconds,
        "feedback_frames_per_s": feedback_frames / wall,
        "host_load_percent": host_load,
        "feedback_load_percent": feedback_load,
        "total_load_percent": host_load + feedback_load,
        "target_load_percent": TARGET_LOAD_PERCENT,
        "meets_target": host_load <= TARGET_LOAD_PERCENT,
        "load_method": "exact bits per frame (stuff bits, CRC, delimiters, ACK, EOF, 3-bit intermission) "
                       f"at {bitrate} bit/s; host = commands and gains sent, feedback = 0xB1/0xB2 streamed at "
                       f"{system.feedback_ms} ms",
        "flags": flags,
    }
