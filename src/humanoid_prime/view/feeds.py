"""Where a view gets Prime's state: the run's own topics (``--web``), a running instance's control socket, or
the ROS 2 graph (``prime view --dds``); and where its mode buttons send requests."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.runtime.readout import state_source
from humanoid_prime.runtime.socket import request, request_state

STATE_KEYS = ("position", "mode", "flags", "levels")
READOUT_KEYS = ("elapsed_s", "rate_hz", "update_rate_hz", "effort", "drives")  # Readout.as_dict's


def manager_source(manager: ControllerManager) -> tuple[Callable[[], dict[str, Any]], Callable[[], None]]:
    """The run's own latest state (one copy of 14 positions per tick, the readout when asked) and the function that
    detaches it."""
    return state_source(manager)


def socket_source(path: Any) -> tuple[Callable[[], dict[str, Any]], Callable[[str], Any]]:
    """A running instance's state over its control socket, and its mode requests (what `prime switch` does)."""
    def state() -> dict[str, Any]:
        reply = request_state(path)
        return {key: reply[key] for key in (*STATE_KEYS, *READOUT_KEYS) if key in reply}

    def mode(name: str) -> Any:
        return request(path, {"op": "mode", "mode": name})

    return state, mode


class DdsSource:
    """Prime's topics from the ROS 2 graph; mode buttons publish on /prime/mode_request."""

    def __init__(self, robot: Robot, domain: int | None) -> None:
        from humanoid_prime.control.topics import CONTROL_MODE, JOINT_STATES, SAFETY_STATUS
        from humanoid_prime.dds import messages as msg
        from humanoid_prime.dds.graph import MODE_REQUEST
        from humanoid_prime.dds.node import DdsNode

        self._msg = msg
        self.names = list(robot.names)
        self.node = DdsNode(domain)
        self._joint_states = self.node.reader(JOINT_STATES, msg.JointState)
        self._mode = self.node.reader(CONTROL_MODE, msg.String, latched=True, depth=1)
        self._safety = self.node.reader(SAFETY_STATUS, msg.DiagnosticArray, latched=True, depth=1)
        self._requests = self.node.writer(MODE_REQUEST, msg.String)
        self.latest: dict[str, Any] = {}

    def __call__(self) -> dict[str, Any]:
        from humanoid_prime.dds.node import take

        states = take(self._joint_states, 256)
        if states and list(states[-1].name) == self.names:
            self.latest["position"] = np.asarray(states[-1].position, dtype=np.float64)
            if len(states[-1].effort) == len(self.names):
                self.latest["effort"] = [float(v) for v in states[-1].effort]
        for sample in take(self._mode, 8):
            self.latest["mode"] = sample.data
        for sample in take(self._safety, 8):
            flags, levels = {}, {}
            for status in sample.status:
                for value in status.values:
                    key = f"{status.name.removeprefix('prime/')}/{value.key}"
                    flags[key] = value.value
                    levels[key] = "WARN" if status.level == self._msg.DiagnosticStatus.WARN else "ERROR"
            self.latest.update(flags=flags, levels=levels)
        if "position" not in self.latest:
            raise ConnectionError("no /prime/joint_states on the ROS 2 graph yet")
        return dict(self.latest)

    def request_mode(self, name: str) -> None:
        self._requests.write(self._msg.String(data=name))

    def close(self) -> None:
        self.node.close()
