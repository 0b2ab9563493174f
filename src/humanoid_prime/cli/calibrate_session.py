"""What every phase of a ``prime calibrate`` run shares: the joints asked for, the virtual Prime, each phase's
session and the one recording of the whole run."""

from __future__ import annotations

import argparse
import contextlib
import time
from typing import TYPE_CHECKING

from humanoid_prime.calibration.workflow import tracked_joints
from humanoid_prime.cli.addons import Addons, Run
from humanoid_prime.config.calibration import Calibration
from humanoid_prime.config.robot import Robot
from humanoid_prime.runtime.session import BringupOptions, Session, open_session, plan_session
from humanoid_prime.runtime.socket import ControlServer

if TYPE_CHECKING:
    from humanoid_prime.virtual.harness import VirtualPrime
    from humanoid_prime.virtual.ring.options import RingSettings

# The documented procedure (DESIGN §5): the eRob arms on EtherCAT first, then the wrists on CAN alone, since
# limp wrists flop while an arm is swept. --backends ec or can runs one of the two phases.
PHASES = {"all": ("ec", "can"), "ec": ("ec",), "can": ("can",)}


def joint_list(text: str | None) -> list[str]:
    return [j.strip() for j in (text or "").split(",") if j.strip()]



def run_joints(robot: Robot, backends: str) -> tuple[str, ...]:
    """The joints every phase of a run on ``backends`` tracks, in canonical order."""
    tracked = {joint for phase in PHASES[backends] for joint in tracked_joints(robot, phase)}
    return tuple(joint for joint in robot.names if joint in tracked)


def virtual_prime(args: argparse.Namespace, ring: RingSettings, stack: contextlib.ExitStack) -> VirtualPrime | None:
    """The virtual Prime for the whole run with --emulate (None on the robot)."""
    if not args.emulate:
        return None
    from humanoid_prime.virtual.harness import attach_virtual_prime

    return attach_virtual_prime(stack, hardware_file=args.hardware, truth_file=args.truth, ring_options=ring,
                                avoid_cpu=args.cpu)


class Recording:
    """``--record``: one file for the whole run, each phase's session attached in turn."""

    def __init__(self, args: argparse.Namespace, stack: contextlib.ExitStack) -> None:
        self.args = args
        self.stack = stack
        self.run: Run | None = None

    def attach(self, session: Session, stack: contextlib.ExitStack) -> None:
        if self.run is None:
            # Stamps in the system clock, as on the robot; the file is finished when the run ends.
            self.run = Run(session.manager, report=print, epoch_offset=time.time() - time.monotonic())
            Addons().attach(self.run, self.args, self.stack, names=("record",))
        self.run.follow(session.manager, stack)


def open_phase(args: argparse.Namespace, backends: str, calibration: Calibration, virtual: VirtualPrime | None,
               server: ControlServer, stack: contextlib.ExitStack) -> Session:
    """A broadcaster-only session on ``backends`` with ``calibration``, answering on ``server``."""
    # The loop keeps every drive's output watchdog fed while the arm is swept: on a busy computer it needs the
    # same real-time scheduling as a bring-up (a 100 ms stall faults every drive with 0xA000).
    options = BringupOptions(backends=backends, calibration=calibration, broadcaster_only=True,
                             emulated=virtual is not None, hardware_file=args.hardware,
                             controllers_file=args.controllers, control_socket=args.socket,
                             realtime=args.realtime, cpu=args.cpu, config=args.config.as_dict(),
                             state_folder=args.config.folder.state, ec_mailbox=args.ec_mailbox)
    if virtual is not None:
        virtual.wire_into(options)
    plan = plan_session(options)
    plan.control = server
    return open_session(plan, stack)

