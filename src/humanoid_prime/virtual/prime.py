"""``python -m humanoid_prime.virtual``: the virtual Prime process.

Ten emulated eRob drives answer EtherCAT frames on one interface, four emulated Sito motors answer on a
CAN bus, and all fourteen move one MuJoCo plant, advanced at 1 kHz by the ring's loop. The control
channel (newline JSON on a UNIX socket) adds whole-robot operations to the ring's own: ``joints`` (true
joint angles), ``push`` (a constant external torque on a joint, a test load), ``hand`` (an operator's
hand moving a joint at a set speed with a capped force), ``gravity`` (on/off), ``sito`` (fault injection
on one wrist) and ``truth`` (the wiring and factory offsets it was given).
"""

from __future__ import annotations

import argparse
import sys
from typing import TypedDict

import can

from humanoid_prime.config.calibration import load_calibration
from humanoid_prime.config.robot import load_robot
from humanoid_prime.errors import PrimeError
from humanoid_prime.virtual.plant import PrimeWorld, ring_order, truth_calibration
from humanoid_prime.virtual.ring.__main__ import wait_for_interface
from humanoid_prime.virtual.ring.options import RingOptions
from humanoid_prime.virtual.ring.ring import Ring
from humanoid_prime.virtual.ring.server import EmulatorServer, bring_up, raise_to_realtime, run_until_signalled
from humanoid_prime.virtual.sito import SitoEmulator

EMULATOR_PRIORITY = 70  # SCHED_FIFO, below the control loop's 80


class SitoFaults(TypedDict):
    """One wrist motor's injected faults (the control channel's ``sito``)."""

    can_id: int
    silent: bool
    drop_fraction: float
    garbage: bool
    late_s: float


class VirtualPrimeServer(EmulatorServer):
    def __init__(self, ring: Ring, interface: str, control_path: str, world: PrimeWorld,
                 sito: SitoEmulator | None, parent_fd: int | None = None) -> None:
        super().__init__(ring, interface, control_path, parent_fd=parent_fd)
        self.world = world
        self.sito = sito

    def _op_joints(self) -> dict[str, float]:
        return self.world.joint_positions()

    def _op_push(self, joint: str, torque_nm: float) -> None:
        self.world.robot.index(joint)  # KeyError names the known joints
        self.world.set_joint_external(joint, float(torque_nm))

    def _op_hand(self, joint: str, speed_rad_s: float, force_nm: float) -> None:
        self.world.robot.index(joint)
        self.world.set_hand(joint, float(speed_rad_s), float(force_nm))

    def _op_gravity(self, enabled: bool) -> list[float]:
        """Switch gravity in the plant off (a load test measures the drives alone) or back on."""
        return self.world.set_gravity(bool(enabled))

    def _op_truth(self) -> dict[str, dict[str, float]]:
        return {j: {"direction": c.direction, "homing_offset": c.homing_offset}
                for j, c in self.world.truth.joints.items()}

    def _op_sito(self, joint: str, silent: bool | None = None, drop_fraction: float | None = None,
                 garbage: bool | None = None, late_s: float | None = None) -> SitoFaults:
        if self.sito is None:
            raise KeyError("this virtual Prime has no Sito motors")
        can_id = self.world.robot.hardware.mit_joints[joint]
        motor = self.sito.motors[can_id]
        if silent is not None:
            motor.silent = bool(silent)
        if drop_fraction is not None:
            motor.drop_fraction = float(drop_fraction)
        if garbage is not None:
            motor.garbage = bool(garbage)
        if late_s is not None:
            motor.late_s = float(late_s)
        return {"can_id": can_id, "silent": motor.silent, "drop_fraction": motor.drop_fraction,
                "garbage": motor.garbage, "late_s": motor.late_s}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m humanoid_prime.virtual",
                                     description="Run the virtual Prime: eRob ring, Sito motors, one MuJoCo plant.")
    parser.add_argument("--iface", required=True, help="interface the EtherCAT master's frames arrive on")
    parser.add_argument("--control", required=True, metavar="PATH", help="UNIX socket for the control channel")
    parser.add_argument("--wait-iface", type=float, default=0.0, metavar="SECONDS")
    parser.add_argument("--parent-fd", type=int, metavar="FD",
                        help="read end of a pipe from the parent: exit when it closes (the parent died)")
    parser.add_argument("--hardware", metavar="FILE", help="hardware file (default: bundled)")
    parser.add_argument("--can-interface", default="udp_multicast", help="python-can interface of the Sito bus")
    parser.add_argument("--can-channel", default="239.74.163.2", help="python-can channel of the Sito bus")
    parser.add_argument("--truth", metavar="FILE",
                        help="calibration file giving the virtual robot's wiring directions and factory offsets "
                             "(raw = direction * joint + offset); default identity")
    parser.add_argument("--pose", default="", metavar="J=RAD,...", help="initial joint angles")
    RingOptions.add_arguments(parser)
    return parser


def _pose(text: str) -> dict[str, float]:
    pose = {}
    for item in filter(None, text.split(",")):
        joint, _, value = item.partition("=")
        pose[joint.strip()] = float(value)
    return pose


def answer_in_hardware_time() -> None:
    """Real-time scheduling for the emulator (and the threads it starts), just below the control loop's, where
    allowed: drives answer in hardware time however busy the host is, and a master's state checks, which
    pysoem makes while holding its interpreter, then end as quickly as they would on the robot."""
    raise_to_realtime(EMULATOR_PRIORITY)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        options = RingOptions.from_args(args)
        robot = load_robot(args.hardware)
        truth = truth_calibration(robot, load_calibration(robot.hardware, args.truth) if args.truth else None)
        if options.slaves != len(robot.hardware.erob_slaves):
            raise PrimeError(f"--slaves {options.slaves} but the hardware file has "
                             f"{len(robot.hardware.erob_slaves)} eRob")
        world = PrimeWorld(robot, truth, physics_dt=options.physics_dt_s, initial_pose=_pose(args.pose))
        ring_plant = world.plant(ring_order(robot), clock=True)
    except (PrimeError, ValueError) as exc:
        print(f"virtual prime: {exc}", file=sys.stderr)
        return 2
    if not wait_for_interface(args.iface, args.wait_iface):
        print(f"virtual prime: interface {args.iface} does not exist", file=sys.stderr)
        return 1
    answer_in_hardware_time()
    bus = can.Bus(interface=args.can_interface, channel=args.can_channel)
    sito = SitoEmulator.for_robot(robot, bus, world.plant(robot.hardware.sito_joints),
                                  rate_hz=1.0 / options.physics_dt_s, world_step=world.step)
    world.attach(sito.step)  # each physics step is one firmware tick, which steps the world
    try:
        bring_up(args.iface)
        server = VirtualPrimeServer(Ring(options, plant=ring_plant), args.iface, args.control, world, sito,
                                    parent_fd=args.parent_fd)
    except OSError as exc:
        bus.shutdown()
        print(f"virtual prime: cannot serve on {args.iface}: {exc} (raw sockets need root or CAP_NET_RAW)",
              file=sys.stderr)
        return 1

    try:
        run_until_signalled(server)
    finally:
        bus.shutdown()
    return 0
