"""The five control modes and the controllers that implement them."""

from __future__ import annotations

from enum import StrEnum


class Mode(StrEnum):
    ZERO_TORQUE = "ZERO_TORQUE"
    DAMPING = "DAMPING"
    STANDBY = "STANDBY"
    LOCOMOTION = "LOCOMOTION"
    REMOTE = "REMOTE"

    @property
    def controller(self) -> str:
        return MODE_CONTROLLERS[self]

    @classmethod
    def parse(cls, text: str) -> Mode:
        """Accept ``STANDBY``, ``standby`` or a controller name such as ``standby_controller``."""
        key = text.strip()
        for mode in cls:
            if key.upper() == mode.value or key == mode.controller:
                return mode
        names = ", ".join(m.value for m in cls)
        raise ValueError(f"unknown mode {text!r}; expected one of {names}")


MODE_CONTROLLERS: dict[Mode, str] = {
    Mode.ZERO_TORQUE: "zero_torque_controller",
    Mode.DAMPING: "damping_controller",
    Mode.STANDBY: "standby_controller",
    Mode.LOCOMOTION: "locomotion_controller",
    Mode.REMOTE: "remote_policy_controller",
}

JOINT_STATE_BROADCASTER = "joint_state_broadcaster"
