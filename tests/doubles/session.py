"""Prime without a network for whole-session tests: the description's EtherCAT block is built on the master
double (ten CiA402 drives with gain registers), the Sito block talks to emulated motors on a private
virtual CAN channel, both through the runtime's own component registry."""

from __future__ import annotations

import contextlib
import struct

import can

from doubles.mailboxes import FACTORY_WINDOW
from doubles.master import SWITCH_ON_DISABLED, FakeMaster
from humanoid_prime.config.description import ETHERCAT_BLOCK
from humanoid_prime.config.robot import Robot
from humanoid_prime.drivers.erob.objects import (
    BUS_GAIN_GATE,
    FOLLOWING_ERROR_WINDOW,
    POS_LOOP_GAIN,
    VEL_LOOP_GAIN,
    VEL_LOOP_INTEGRAL,
)
from humanoid_prime.drivers.ethercat.system import EthercatSystem
from humanoid_prime.runtime import registry
from humanoid_prime.runtime.session import BringupOptions, Session, claim_control_socket, open_session, plan_session
from humanoid_prime.virtual.sito import SitoEmulator

FACTORY_REGISTERS = (300, 94, 5)  # pos_reg, vel_reg, integral


class DoubledRobot:
    """Opens sessions on the doubles; ``master`` is the master double of the last session's EtherCAT block."""

    def __init__(self, robot: Robot, channel: str, monkeypatch, stack: contextlib.ExitStack) -> None:
        self.robot = robot
        self.channel = channel
        self.stack = stack
        self.master: FakeMaster | None = None
        bus = can.Bus(interface="virtual", channel=channel)
        stack.callback(bus.shutdown)
        self.emulator = SitoEmulator.for_robot(robot, bus)
        self.emulator.start()
        stack.callback(self.emulator.stop)
        monkeypatch.setitem(registry.COMPONENTS, ETHERCAT_BLOCK, self._ethercat)

    def _ethercat(self, settings: registry.ComponentSettings) -> EthercatSystem:
        master = FakeMaster(update_rate=settings.update_rate, bringup_rate=settings.bringup_rate)
        for position in range(len(master.found)):
            _factory_objects(master, position)
        self.master = master
        return EthercatSystem(settings.robot, settings.calibration, update_rate=settings.update_rate,
                              bringup_rate=settings.bringup_rate, master=master)

    def power_cycle(self, position: int) -> None:
        """The drive at ``position`` lost power and came back: factory gate, window and gains, switch-on
        disabled (its slave back in OP at once)."""
        assert self.master is not None
        _factory_objects(self.master, position)
        self.master.statusword[position] = SWITCH_ON_DISABLED

    def options(self, **fields: object) -> BringupOptions:
        """Options of a run on the doubles: the robot as on real hardware, its calibration the identity template,
        so the modes that move joints are allowed as ``--uncalibrated`` does (unless ``uncalibrated`` says)."""
        return BringupOptions(can_interface="virtual", can_channel=self.channel, **{"uncalibrated": True, **fields})

    def open(self, **fields: object) -> Session:
        """A session on the doubles, torn down with the test; with ``control_socket`` it claims that socket
        first, as the commands do."""
        plan = plan_session(self.options(**fields))
        if plan.options.control_socket is not None:
            claim_control_socket(plan, self.stack)
        return open_session(plan, self.stack)


def _factory_objects(master: FakeMaster, position: int) -> None:
    for address, value in zip((POS_LOOP_GAIN, VEL_LOOP_GAIN, VEL_LOOP_INTEGRAL), FACTORY_REGISTERS, strict=True):
        master.objects[(position, *address)] = struct.pack("<H", value)  # UNSIGNED16, as the EDS has them
    master.objects[(position, *BUS_GAIN_GATE)] = struct.pack("<I", 0)
    master.objects[(position, FOLLOWING_ERROR_WINDOW, 0)] = struct.pack("<i", FACTORY_WINDOW)
