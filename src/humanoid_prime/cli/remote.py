"""``prime remote``: the reference REMOTE client. Streams MIT commands over DDS to a running Prime (``prime sim
--dds --dds-control`` or ``prime bringup --dds --dds-control``, on this machine or another in the same ROS 2
domain and namespace) and prints what Prime publishes. The client itself is ``dds/remote.py``."""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import (
    SECONDS,
    add_config_options,
    add_domain_option,
    add_json_option,
    output_file,
    real,
)
from humanoid_prime.config.controllers import load_controllers
from humanoid_prime.config.robot import load_robot
from humanoid_prime.control.rate import Rate
from humanoid_prime.dds.domain import domain_id, node_namespace
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_text
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.signals import stop_on_signals

if TYPE_CHECKING:  # the client is imported when the command runs
    from humanoid_prime.config.robot import Robot
    from humanoid_prime.dds.remote import RemoteClient, Tracking

DEFAULT_WAVE = "left_elbow_pitch,right_elbow_pitch,left_wrist_pitch,right_wrist_pitch"
STATUS_EVERY_S = 1.0


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "remote", help=summary("remote"),
        description="The reference REMOTE client: a separate DDS participant that streams "
                    "prime_msgs/MitCommand on /remote_policy_controller/command to a Prime started with --dds "
                    "--dds-control, "
                    "asks for REMOTE on /prime/mode_request, and prints the joint states, mode and safety status "
                    "it receives. The motion starts at the measured position, moves to the pose over --ramp "
                    "seconds, then holds it (--amplitude 0) or waves the --wave joints about it.")
    add_domain_option(p, with_dds=False)
    p.add_argument("--namespace", metavar="NAME", help="the ROS 2 namespace of the Prime to drive (default: none)")
    p.add_argument("--pose", metavar="NAME", help="standby pose to hold or wave about (default: the default pose)")
    p.add_argument("--wave", metavar="JOINT,...", default=DEFAULT_WAVE,
                   help=f"joints that wave about the pose (default: {DEFAULT_WAVE})")
    p.add_argument("--amplitude", type=real(at_least=0.0, at_most=1.0), default=0.3, metavar="RAD",
                   help="wave amplitude (default: 0.3; 0 holds the pose)")
    p.add_argument("--frequency", type=real(above=0.0, at_most=2.0), default=0.5, metavar="HZ",
                   help="wave frequency (default: 0.5)")
    p.add_argument("--ramp", type=SECONDS, default=2.0, metavar="S",
                   help="seconds from the measured position to the pose (default: 2)")
    p.add_argument("--rate", type=real(above=0.0, at_most=1000.0), default=50.0, metavar="HZ",
                   help="commands per second (default: 50)")
    p.add_argument("--sito-kp", type=real(at_least=0.0, at_most=50.0), metavar="NM_PER_RAD",
                   help="Sito wrist stiffness sent every command (default: the LOCOMOTION wrist gains)")
    p.add_argument("--sito-kd", type=real(at_least=0.0, at_most=5.0), metavar="NMS_PER_RAD",
                   help="Sito wrist damping sent every command (default: the LOCOMOTION wrist gains)")
    p.add_argument("--no-switch", action="store_true", help="do not ask for REMOTE (switch yourself)")
    p.add_argument("--duration", type=SECONDS, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--wait", type=SECONDS, default=10.0, metavar="S",
                   help="seconds to wait for Prime's joint states before giving up (default: 10)")
    p.add_argument("--summary", metavar="FILE", type=output_file, help="write the run's figures as JSON")
    add_config_options(p, controllers=True)
    add_json_option(p)
    p.set_defaults(func=run)


def _wave_mask(robot: Robot, text: str) -> npt.NDArray[np.bool_]:
    mask = np.zeros(robot.n, dtype=bool)
    for name in (item.strip() for item in text.split(",") if item.strip()):
        if name not in robot.names:
            raise PrimeError(f"--wave: {name!r} is not a joint of Prime (joints: {', '.join(robot.names)})")
        mask[robot.index(name)] = True
    return mask


def run(args: argparse.Namespace) -> int:
    from humanoid_prime.control.controller import gain_rows, pose_array
    from humanoid_prime.dds.remote import Motion, RemoteClient, Tracking

    robot = load_robot(args.hardware, use_sim=True)
    config = load_controllers(robot.names, args.controllers)
    poses = config.standby.poses
    pose_name = args.pose or config.standby.default_pose
    if pose_name not in poses:
        raise PrimeError(f"--pose: no pose {pose_name!r} (poses: {', '.join(poses)})")
    wave = _wave_mask(robot, args.wave)
    domain = domain_id(args.domain)
    namespace = node_namespace(args.namespace)
    sito_kp = config.locomotion.sito_kp if args.sito_kp is None else args.sito_kp
    sito_kd = config.locomotion.sito_kd if args.sito_kd is None else args.sito_kd
    stiffness, damping = gain_rows(robot, (config.remote.erob_kp, config.remote.erob_kd), (sito_kp, sito_kd))
    zeros = np.zeros(robot.n)
    out = sys.stderr if args.json else sys.stdout
    stop = threading.Event()

    with stop_on_signals(stop), RemoteClient(robot, domain=domain, namespace=namespace,
                                                    command_topic=config.remote.topic) as client:
        print(f"prime remote: domain {domain}, waiting for /prime/joint_states ...", file=out, flush=True)
        seen = client.seen.position if client.wait_for_joint_states(args.wait, sleep=stop.wait) else None
        if seen is None:
            raise PrimeError(f"no joint states from Prime on ROS 2 domain {domain} within {args.wait:g} s (is it "
                             "running with --dds, in the same domain and namespace, reachable on this network?)")
        motion = Motion(start=np.clip(seen, robot.lower, robot.upper),
                        pose=pose_array(robot, poses[pose_name]), lower=robot.lower, upper=robot.upper, wave=wave,
                        amplitude=args.amplitude, frequency=args.frequency, ramp=args.ramp)
        began = time.monotonic()
        tracking = Tracking(wave if args.amplitude > 0 else np.ones(robot.n, dtype=bool),
                            lambda at: motion.target(at - began)[0], since=began + args.ramp + 1.0)
        client.on_joint_state = tracking
        rate = Rate(args.rate, sleep=stop.wait)
        switched = args.no_switch
        next_status = began
        while not stop.is_set():
            rate.wait()
            now = time.monotonic()
            t = now - began
            if args.duration is not None and t >= args.duration:
                break
            position, velocity = motion.target(t)
            client.send(position, velocity, zeros, stiffness, damping)
            client.poll()
            if not switched and client.sent >= 2:  # commands are flowing: REMOTE starts on a fresh one
                client.request_mode(Mode.REMOTE.value)
                switched = True
            if now >= next_status and not args.json:
                next_status = now + STATUS_EVERY_S
                print(_status_line(client, tracking, t), file=out, flush=True)
        client.poll()
        seconds = round(time.monotonic() - began, 3)
        summary = {
            "domain": domain, "commands_sent": client.sent, "seconds": seconds,
            "joint_states_received": client.seen.joint_states, "joint_state_rate_hz": client.seen.joint_state_rate(),
            "modes_seen": client.seen.modes, "safety_at_end": [list(s) for s in client.seen.safety],
            "tracking": tracking.as_dict(), "pose": pose_name, "wave": [n for n, w in zip(robot.names, wave,
                                                                                         strict=True) if w],
            "amplitude_rad": args.amplitude, "frequency_hz": args.frequency, "overruns": rate.overruns,
        }
    if args.summary:
        atomic_write_text(args.summary, json.dumps(summary, indent=2) + "\n")
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"sent {client.sent} commands in {seconds:.1f} s; received "
              f"{client.seen.joint_states} joint states; modes seen: {' -> '.join(client.seen.modes)}")
    return 0


def _status_line(client: RemoteClient, tracking: Tracking, t: float) -> str:
    seen = client.seen
    rate = seen.joint_state_rate()
    problems = [f"{name} {level}: {message}" for name, level, message in seen.safety if level != "OK"]
    track = tracking.as_dict()
    following = ""
    if track["residual_rms_rad"] is not None:
        following = f"  tracking rms {track['residual_rms_rad']:.3f} rad (offset {track['offset_rad']:.3f})"
    return (f"t {t:6.1f} s  sent {client.sent:6d}  joint states {seen.joint_states:6d}"
            f"{f' ({rate:.0f} Hz)' if rate else ''}  mode {seen.mode or '?'}{following}"
            f"  safety: {'; '.join(problems) or 'ok'}")
