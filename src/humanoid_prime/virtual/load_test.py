"""Load test on the virtual Prime: realised eRob stiffness in STANDBY, by pushing the plant.

With gravity off in the plant, each eRob joint is pushed with +torque and -torque and the deflection read;
realised kp = 2*torque / (q(+) - q(-)). Runs in its own thread while the control loop runs; friction
biases the figure low by about friction/torque (0.1/5 = 2 % on the eRob joints).
"""

from __future__ import annotations

import collections
import contextlib
import threading
import time
from collections.abc import Sequence
from typing import TypedDict

import numpy as np

from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.session import Session
from humanoid_prime.virtual.harness import PrimeControl


class Stiffness(TypedDict):
    """One joint's load test: its deflection under +/- ``torque_nm`` and the stiffness that makes."""

    joint: str
    torque_nm: float
    deflection_rad: float
    kp_nominal: float
    kp_realised: float  # NaN: it did not deflect
    ratio: float  # realised / nominal
    torque_efficiency: float


SETTLED_RAD = 5e-4  # a joint that moved less than this over SETTLE_WINDOW_S has settled under its push
SETTLE_WINDOW_S = 0.5


def measure_stiffness(session: Session, control: PrimeControl, joints: Sequence[str], *, torque_nm: float = 5.0,
                      settle_s: float = 3.0, average_s: float = 1.0, settle_timeout_s: float = 20.0,
                      stop: threading.Event | None = None) -> list[Stiffness]:
    """Nominal against realised kp per joint of ``joints`` (eRob joints of the running ``session``)."""
    robot, manager = session.robot, session.manager
    for joint in joints:
        if joint not in robot.hardware.erob_slaves:
            raise PrimeError(f"load test: {joint!r} is not an eRob joint "
                             f"(eRob joints: {', '.join(robot.hardware.erob_joints)})")
    kp_nominal, _ = session.config.mode_gains()[Mode.STANDBY]
    efficiency = robot.hardware.torque_efficiency
    results: list[Stiffness] = []

    stop = stop or threading.Event()

    def settle_and_average(i: int) -> float:
        """The joint's mean position once it has settled: at least ``settle_s``, then until it moved less than
        SETTLED_RAD over SETTLE_WINDOW_S (on a busy host the emulated robot's physics falls behind the clock, and
        a fixed wait would average a joint still on its way)."""
        if stop.wait(settle_s):
            raise PrimeError("load test stopped before it finished")
        window: collections.deque[tuple[float, float]] = collections.deque()
        deadline = time.monotonic() + settle_timeout_s
        while time.monotonic() < deadline:
            now, q = time.monotonic(), float(manager.resources.state.position[i])
            window.append((now, q))
            while window and now - window[0][0] > SETTLE_WINDOW_S:
                window.popleft()
            if now - window[0][0] >= 0.9 * SETTLE_WINDOW_S and \
                    max(p for _t, p in window) - min(p for _t, p in window) < SETTLED_RAD:
                break
            if stop.wait(0.01):
                raise PrimeError("load test stopped before it finished")
        samples: list[float] = []
        end = time.monotonic() + average_s
        while time.monotonic() < end:
            samples.append(float(manager.resources.state.position[i]))
            time.sleep(0.01)
        return float(np.mean(samples))

    control.gravity(False)
    try:
        for joint in joints:
            i = robot.index(joint)
            control.push(joint, torque_nm)
            q_plus = settle_and_average(i)
            control.push(joint, -torque_nm)
            q_minus = settle_and_average(i)
            control.push(joint, 0.0)
            deflection = q_plus - q_minus
            kp = 2.0 * torque_nm / deflection if deflection > 0 else float("nan")
            ratio = kp / kp_nominal if kp_nominal > 0 else float("nan")
            results.append({"joint": joint, "torque_nm": torque_nm, "deflection_rad": deflection,
                            "kp_nominal": kp_nominal, "kp_realised": kp, "ratio": ratio,
                            "torque_efficiency": efficiency})
    finally:
        for joint in joints:
            with contextlib.suppress(PrimeError):
                control.push(joint, 0.0)
        control.gravity(True)
    return results
