"""LOCOMOTION: an in-process ONNX policy. Every tick: pack the observation, infer, scale the action
around the default pose, and command it with the policy's gains (eRob: the fixed mode gains, which
the impedance manager writes per mode; Sito: ``sito_kp``/``sito_kd`` every tick).

Targets are clipped to the joint limits, and blended in from the pose measured on entry over
``ENTRY_BLEND_S`` so that entering the mode far from the default pose does not step the target.
A non-finite action raises ControllerError (the manager falls back to DAMPING in the same tick).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.controller import Controller, capture_position, gain_rows
from humanoid_prime.control.controllers.standby import min_jerk
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.policy import Policy
from humanoid_prime.control.topics import TopicBus
from humanoid_prime.errors import ControllerError
from humanoid_prime.modes import Mode

ENTRY_BLEND_S = 1.0


class LocomotionController(Controller):
    def __init__(self, policy_path: Path, default_pose: npt.NDArray[np.float64], action_scale: float, erob_kp: float,
                 erob_kd: float, sito_kp: float, sito_kd: float) -> None:
        super().__init__(Mode.LOCOMOTION.controller, Mode.LOCOMOTION)
        self.policy_path = Path(policy_path)
        self.default_pose = np.asarray(default_pose, dtype=np.float64)
        self.action_scale = action_scale
        self.erob_gains = (erob_kp, erob_kd)
        self.sito_gains = (sito_kp, sito_kd)

    def on_configure(self, robot: Robot, topics: TopicBus) -> None:
        self.policy = Policy(self.policy_path, robot.names)
        self.names = robot.names
        self._kp, self._kd = gain_rows(robot, self.erob_gains, self.sito_gains)
        self._lower = robot.lower
        self._upper = robot.upper
        self._relative = np.zeros(robot.n)
        self._last_action = np.zeros(robot.n)
        self._target = np.zeros(robot.n)
        self._entry = np.zeros(robot.n)
        self._finite = np.zeros(robot.n, dtype=bool)
        self.t0 = 0.0

    def on_activate(self, state: StateArrays, now: float) -> None:
        capture_position(self.names, state, self._entry, "")
        self._last_action[:] = 0.0
        self.t0 = now

    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        np.subtract(state.position, self.default_pose, out=self._relative)
        self.policy.pack(self._relative, state.velocity, self._last_action, now - self.t0)
        action = self.policy.run()
        np.isfinite(action, out=self._finite)
        if not self._finite.all():
            raise ControllerError(f"policy produced a non-finite action for "
                                  f"{self.names[int(np.argmin(self._finite))]}")
        np.copyto(self._last_action, action)
        np.multiply(self._last_action, self.action_scale, out=self._target)
        np.add(self._target, self.default_pose, out=self._target)
        np.clip(self._target, self._lower, self._upper, out=self._target)
        blend, _ = min_jerk((now - self.t0) / ENTRY_BLEND_S)
        np.subtract(self._target, self._entry, out=command.position)
        np.multiply(command.position, blend, out=command.position)
        np.add(command.position, self._entry, out=command.position)
        command.velocity[:] = 0.0
        command.effort[:] = 0.0
        np.copyto(command.stiffness, self._kp)
        np.copyto(command.damping, self._kd)
