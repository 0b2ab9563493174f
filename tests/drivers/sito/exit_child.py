"""A process that activates the wrists over udp_multicast and then leaves in the way it is told.

Run by test_exit.py: ``python exit_child.py GROUP PORT normal|exception|signal``.
"""

from __future__ import annotations

import faulthandler
import sys
import time

import can

from humanoid_prime.config.calibration import identity_calibration
from humanoid_prime.config.robot import load_robot
from humanoid_prime.control.interfaces import CommandArrays
from humanoid_prime.drivers.sito.system import SitoSystem


def main() -> None:
    faulthandler.dump_traceback_later(20.0, exit=True)  # a hang shows where every thread is, then ends
    group, port, how = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    robot = load_robot()
    bus = can.Bus(interface="udp_multicast", channel=group, port=port)
    system = SitoSystem(robot, identity_calibration(robot.hardware), update_rate=50.0, bus=bus,
                        rx_timeout_ms=2000.0)
    system.configure()
    system.activate()
    command = CommandArrays(robot.n)
    command.stiffness[system.indices] = 20.0
    command.damping[system.indices] = 2.0
    system.write(0.0, command)
    print("active", flush=True)
    if how == "exception":
        raise RuntimeError("the control loop failed")
    if how == "signal":
        while True:
            system.write(0.0, command)
            time.sleep(0.02)
    # normal: leave without deactivating


if __name__ == "__main__":
    main()
