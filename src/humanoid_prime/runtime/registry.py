"""Hardware components by the robot description's block name, the way python-can builds a bus from an
interface name: ``PrimeEtherCATSide`` is the eRob ring (``EthercatSystem`` on a SOEM master),
``PrimeSitoCAN`` the Sito wrists (``SitoSystem``), ``MujocoSystem`` the simulated Prime.

Each builder imports its bus library only when it runs, so a simulation never loads pysoem and a
calibration of the wrists never opens the EtherCAT NIC.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from humanoid_prime.config.calibration import Calibration
from humanoid_prime.config.description import ETHERCAT_BLOCK, MUJOCO_BLOCK, SITO_BLOCK
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.errors import PrimeError


@dataclass(frozen=True)
class ComponentSettings:
    """What the builders need beyond the robot: rates, calibration and where each bus is."""

    robot: Robot
    calibration: Calibration
    update_rate: float
    bringup_rate: float = 1000.0
    ethercat_interface: str | None = None  # default: the hardware file's
    ethercat_mailbox: str | None = None  # prime or soem; default: the hardware file's
    sync0_period_s: float | None = None  # cross-check only: SYNC0 is derived from update_rate
    parallel_sdo: bool = True
    erob_config_dir: str | Path | None = None  # also write the folded per-slave configs here
    can_interface: str | None = None  # python-can interface; default: the hardware file's
    can_channel: str | None = None
    physics_rate: float = 1000.0
    model_path: str | Path | None = None
    initial_pose: Mapping[str, float] | None = None
    emulated: bool = False  # the buses lead to the virtual Prime: its faults are the emulator's, not a cable's


def _ethercat(settings: ComponentSettings) -> HardwareComponent:
    from humanoid_prime.drivers.ethercat.soem_master import SoemMaster
    from humanoid_prime.drivers.ethercat.system import EthercatSystem

    robot = settings.robot
    interface = settings.ethercat_interface or robot.hardware.ethercat.interface
    master = SoemMaster(interface, update_rate=settings.update_rate, bringup_rate=settings.bringup_rate,
                        sync0_period_s=settings.sync0_period_s, parallel_sdo=settings.parallel_sdo,
                        mailbox=settings.ethercat_mailbox or robot.hardware.ethercat.mailbox)
    return EthercatSystem(robot, settings.calibration, update_rate=settings.update_rate,
                          bringup_rate=settings.bringup_rate, master=master, interface=interface,
                          config_dir=settings.erob_config_dir, emulated=settings.emulated)


def _sito(settings: ComponentSettings) -> HardwareComponent:
    from humanoid_prime.drivers.sito.system import SitoSystem

    return SitoSystem(settings.robot, settings.calibration, update_rate=settings.update_rate,
                      interface=settings.can_interface, channel=settings.can_channel, emulated=settings.emulated)


def _mujoco(settings: ComponentSettings) -> HardwareComponent:
    from humanoid_prime.drivers.mujoco.system import MujocoSystem

    return MujocoSystem(settings.robot, physics_rate=settings.physics_rate, update_rate=settings.update_rate,
                        model_path=settings.model_path, initial_pose=settings.initial_pose)


COMPONENTS: dict[str, Callable[[ComponentSettings], HardwareComponent]] = {
    ETHERCAT_BLOCK: _ethercat,
    SITO_BLOCK: _sito,
    MUJOCO_BLOCK: _mujoco,
}


def build_components(blocks: Sequence[str], settings: ComponentSettings) -> list[HardwareComponent]:
    """One component per block name, in the order given; an unknown name is refused with the known ones."""
    components = []
    for name in blocks:
        builder = COMPONENTS.get(name)
        if builder is None:
            raise PrimeError(f"no hardware component is registered for block {name!r}; "
                             f"known blocks: {', '.join(COMPONENTS)}")
        try:
            settings.robot.description.block(name)
        except KeyError:
            raise PrimeError(f"the robot description ({settings.robot.description.source.name}) declares no "
                             f"{name!r} hardware block") from None
        components.append(builder(settings))
    return components
