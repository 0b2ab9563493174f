"""REMOTE over DDS on the whole doubled robot (the eRob on the master double, the wrists on emulated motors): a
command out of bounds is refused, counted and flagged like any other refusal, and nothing out of bounds reaches
the written command, the Sito CAN frames or the eRob CSP targets."""

from __future__ import annotations

import can
import numpy as np

from humanoid_prime.control.interfaces import POSITION_MARGIN
from humanoid_prime.dds import messages as msg
from humanoid_prime.dds.bridge import bridge_manager
from humanoid_prime.dds.node import DdsNode
from humanoid_prime.drivers.erob.constants import COUNTS_PER_RAD as EROB_COUNTS_PER_RAD
from humanoid_prime.drivers.sito.protocol import (
    COUNTS_PER_RAD,
    SITO_MODELS,
    Command,
    Gains,
    firmware_to_kd,
    firmware_to_kp,
    parse_frame,
)
from humanoid_prime.modes import Mode

from .conftest import wait_for

TOPIC = "/remote_policy_controller/command"
TA40_50 = SITO_MODELS["TA40-50"]


def command(robot, **rows) -> msg.MitCommand:
    """A sound command (mid-range targets, the wrists at kp 5, kd 0.5) with ``rows`` replaced."""
    n = robot.n
    sound = {"position": (robot.lower + robot.upper) / 2, "velocity": np.zeros(n), "effort": np.zeros(n),
             "stiffness": np.full(n, 5.0), "damping": np.full(n, 0.5)}
    sound.update(rows)
    return msg.MitCommand(name=list(robot.names), **{k: [float(v) for v in values] for k, values in sound.items()})


def test_remote_refuses_gains_targets_and_velocities_out_of_bounds_and_none_reaches_a_wire(doubled, domain):
    robot = doubled.robot
    sniffer = can.Bus(interface="virtual", channel=doubled.channel)
    doubled.stack.callback(sniffer.shutdown)
    session = doubled.open()
    manager = session.manager
    bridge = bridge_manager(manager, domain=domain, control=True)
    doubled.stack.callback(bridge.close)
    peer = doubled.stack.enter_context(DdsNode(domain))
    writer = peer.writer(TOPIC, msg.MitCommand)
    assert wait_for(lambda: bool(writer.get_matched_subscriptions()))
    remote = manager.controllers["remote_policy_controller"]
    manager.request_mode(Mode.REMOTE)
    manager.tick()
    writer.write(command(robot))
    assert wait_for(lambda: remote.accepted == 1)
    manager.tick()

    n = robot.n
    bad = [({"stiffness": np.full(n, 1e9)}, "stiffness of left_shoulder_pitch is 1e+09 Nm/rad, beyond its limit"),
           ({"damping": np.full(n, 1e9)}, "damping of left_shoulder_pitch is 1e+09 Nm*s/rad, beyond its limit"),
           ({"position": np.full(n, 1e308), "stiffness": np.zeros(n)},  # limp, as the wrist that went out
            "position target of left_shoulder_pitch is 1e+308 rad, outside its limits"),
           ({"velocity": np.full(n, 1e6)}, "velocity of left_shoulder_pitch is 1e+06 rad/s, beyond its limit")]
    for count, (rows, reason) in enumerate(bad, start=1):
        writer.write(command(robot, **rows))
        assert wait_for(lambda count=count: remote.rejected == count)
        manager.tick()
        assert reason in remote.last_rejection
        assert reason in manager.topics.latest("/safety_status").flags["remote_policy_controller/rejected"]
        assert_within_bounds(manager.resources.command.data, manager.bounds)
    assert (remote.accepted, remote.rejected) == (1, 4)
    assert manager.active_mode is Mode.REMOTE and manager.fallbacks == []
    assert bridge.summary()["topics"][TOPIC]["refused"] == 4

    # What went out on the wires: every Sito frame since the start, the eRob's last frame.
    limits = robot.hardware.command_limits["sito"]
    reach = float(np.max(np.abs([robot.lower, robot.upper]))) + POSITION_MARGIN  # identity calibration
    frames = [parse_frame(m.arbitration_id, m.data)[1] for m in iter(lambda: sniffer.recv(0.0), None)]
    commands = [f for f in frames if isinstance(f, Command)]
    gains = [f for f in frames if isinstance(f, Gains)]
    assert commands and gains
    assert max(abs(c.position_counts) for c in commands) <= reach * COUNTS_PER_RAD
    assert max(abs(c.velocity_counts) for c in commands) <= limits.velocity * COUNTS_PER_RAD
    assert max(firmware_to_kp(g.kp_fw, TA40_50) for g in gains) <= limits.stiffness * (1 + 1e-6)
    assert max(firmware_to_kd(g.kd_fw, TA40_50) for g in gains) <= limits.damping * (1 + 1e-6)
    sent = doubled.master.sent
    for joint in robot.hardware.erob_joints:
        j, ring = robot.index(joint), robot.hardware.erob_slaves[joint]
        target = sent["target_position"][ring] / EROB_COUNTS_PER_RAD
        assert robot.lower[j] - POSITION_MARGIN <= target <= robot.upper[j] + POSITION_MARGIN, joint
        assert abs(sent["velocity_offset"][ring]) <= robot.hardware.command_limits["erob"].velocity * \
            EROB_COUNTS_PER_RAD


def assert_within_bounds(data: np.ndarray, bounds) -> None:
    """The command as written: finite, gains not negative, every row within its joint's bounds."""
    assert np.isfinite(data).all()
    assert (data[3:] >= 0.0).all()
    assert (np.abs(data[1:]) <= bounds.maximum).all()
    assert ((bounds.lower <= data[0]) & (data[0] <= bounds.upper)).all()
