"""The hardware-component interface: one per bus (or one simulation), with a lifecycle.

A component owns a subset of the joints (``joints``, names in canonical order) and the bus behind
them, and applies the calibration itself, so everything above it is in the joint frame. It never
knows which mode is active. It knows the canonical indices of its joints from construction on
(``indices``); the resource manager hands it the global arrays, ``read`` fills ``state[:, indices]``,
``write`` sends ``command[:, indices]``. Both must be non-blocking and allocation-free.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import SafetyFlags
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.errors import LifecycleError, PrimeError


class Lifecycle(enum.Enum):
    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FINALIZED = "finalized"


@dataclass(frozen=True)
class DriveStatus:
    """What a drive with a state machine of its own (an eRob: CiA402 on EtherCAT) last said about itself."""

    joint: str
    statusword: int  # 0x6041, from the last frame read
    error_code: int  # 0x603F, from the last frame read
    al_state: int  # its slave's AL state register (0x0130), from the last supervision pass


class HardwareComponent(SafetyFlags, ABC):
    """Base class of ``MujocoSystem``, ``SitoSystem`` and ``EthercatSystem``."""

    def __init__(self, name: str, robot: Robot, joints: Sequence[str]) -> None:
        super().__init__(name)
        unknown = [joint for joint in joints if joint not in robot.names]
        if unknown:
            raise PrimeError(f"hardware component {name!r} lists unknown joint {unknown[0]!r}; "
                             f"known joints: {', '.join(robot.names)}")
        self.joints = tuple(joints)
        self.indices = np.array([robot.index(joint) for joint in self.joints], dtype=np.intp)
        self.lifecycle = Lifecycle.UNCONFIGURED
        # Seconds of the last read + write spent in bus I/O: the system calls that send and collect frames, with
        # any wait for the wire (and, on an emulated bus, for the emulator); in simulation, the physics steps. The
        # tick's cost minus this is the CPU of our own code.
        self.io_s = 0.0

    # Lifecycle. Subclasses override the on_* hooks; these wrappers keep the state machine honest.
    def configure(self) -> None:
        if self.lifecycle is not Lifecycle.UNCONFIGURED:
            raise LifecycleError(f"{self.name}: configure from {self.lifecycle.value}")
        self.on_configure()
        self.lifecycle = Lifecycle.INACTIVE

    def activate(self) -> None:
        if self.lifecycle is not Lifecycle.INACTIVE:
            raise LifecycleError(f"{self.name}: activate from {self.lifecycle.value}")
        self.on_activate()
        self.lifecycle = Lifecycle.ACTIVE

    def deactivate(self) -> None:
        if self.lifecycle is Lifecycle.ACTIVE:
            try:
                self.on_deactivate()
            finally:
                self.lifecycle = Lifecycle.INACTIVE

    def shutdown(self) -> None:
        if self.lifecycle is Lifecycle.FINALIZED:
            return
        try:
            self.deactivate()
        finally:
            try:
                self.on_shutdown()
            finally:
                self.lifecycle = Lifecycle.FINALIZED

    def on_configure(self) -> None:
        """Open the bus, discover the devices, check they match the configuration."""

    def on_activate(self) -> None:
        """Start exchanging data with the devices (enable drives, send gains, ...)."""

    def on_deactivate(self) -> None:
        """Leave every device safe (limp or holding) and stop commanding it."""

    def on_shutdown(self) -> None:
        """Release the bus."""

    @abstractmethod
    def read(self, now: float, state: StateArrays) -> None:
        """Fill ``state`` at ``self.indices`` with the latest measurements (joint frame); ``io_s`` starts
        counting here."""

    @abstractmethod
    def write(self, now: float, command: CommandArrays) -> None:
        """Send ``command`` at ``self.indices`` to the devices (joint frame in, device frame out)."""

    def latched_faults(self) -> list[str]:
        """Devices of this component in a fault that waits for the operator's reset, one line each."""
        return []

    def reset_faults(self) -> None:
        """Clear latched faults with the next ``write`` (called from the control loop's thread); a device
        whose cause persists faults again. Default: this component's devices latch no faults."""

    def drive_states(self) -> list[DriveStatus]:
        """Each of its drives' own state, for a display, which asks at its own rate from its own thread: read from
        what the loop and the bus supervision left, never computed per tick. Default: no such drives."""
        return []

    def __enter__(self) -> HardwareComponent:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()
