"""Test doubles for the control core: an ideal plant owning some joints, a settable clock, and tiny policies."""

from __future__ import annotations

import functools

import numpy as np

from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.control.hardware import HardwareComponent


@functools.cache
def bundled_robot() -> Robot:
    return load_robot()


class Plant(HardwareComponent):
    """Joints with a settable measured state; records lifecycle events and every command written.

    With ``inertia`` set, each write also integrates the MIT law on a double integrator per joint.
    """

    def __init__(self, name: str, joints: tuple[str, ...], events: list[str] | None = None,
                 inertia: float | None = None) -> None:
        super().__init__(name, bundled_robot(), joints)
        self.position = np.zeros(len(joints))
        self.velocity = np.zeros(len(joints))
        self.effort = np.zeros(len(joints))
        self.events = events if events is not None else []
        self.inertia = inertia
        self.written: list[np.ndarray] = []
        self.faults: list[str] = []  # latched faults; cleared by a reset
        self._last_write: float | None = None

    def on_configure(self) -> None:
        self.events.append(f"{self.name}.configure")

    def on_activate(self) -> None:
        self.events.append(f"{self.name}.activate")

    def on_deactivate(self) -> None:
        self.events.append(f"{self.name}.deactivate")

    def on_shutdown(self) -> None:
        self.events.append(f"{self.name}.shutdown")

    def latched_faults(self) -> list[str]:
        return list(self.faults)

    def reset_faults(self) -> None:
        self.events.append(f"{self.name}.reset_faults")
        self.faults.clear()

    def read(self, now, state) -> None:
        state.position[self.indices] = self.position
        state.velocity[self.indices] = self.velocity
        state.effort[self.indices] = self.effort

    def write(self, now, command) -> None:
        mine = command.data[:, self.indices].copy()
        self.written.append(mine)
        if self.inertia is not None and self._last_write is not None:
            q_cmd, qd_cmd, tau_ff, kp, kd = mine
            tau = kp * (q_cmd - self.position) + kd * (qd_cmd - self.velocity) + tau_ff
            dt = now - self._last_write
            self.velocity += tau / self.inertia * dt
            self.position += self.velocity * dt
            self.effort = tau
        self._last_write = now

    @property
    def last(self) -> np.ndarray:
        """The last command written, rows (position, velocity, effort, stiffness, damping)."""
        return self.written[-1]


class Clock:
    """Time that moves only when told to: by ``sleep``, and by ``step`` on every reading."""

    def __init__(self, start: float = 100.0, step: float = 0.0) -> None:
        self.now = start
        self.step = step

    def __call__(self) -> float:
        self.now += self.step
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(seconds, 1e-6)


def constant_policy(path, robot, actions) -> str:
    """A tiny policy that outputs ``actions`` whatever it observes (one linear layer, zero weights)."""
    from humanoid_prime.control.policy import export_mlp

    terms = ("joint_pos_rel", "joint_vel", "last_action", "phase_sin", "phase_cos")
    weight = np.zeros((robot.n, 3 * robot.n + 2))
    model = export_mlp([(weight, np.broadcast_to(np.asarray(actions, float), (robot.n,)))], robot.names, terms, 1.0)
    path.write_bytes(model.SerializeToString())
    return str(path)


def with_policy(config, policy: str):
    from dataclasses import replace

    return replace(config, locomotion=replace(config.locomotion, policy=policy))
