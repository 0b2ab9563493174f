"""``prime plot``: a recording's commanded against measured position and torque per joint, to a PNG."""

from __future__ import annotations

import argparse

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_config_options, output_file


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "plot", help=summary("plot"),
        description="Read a recording made with --record and draw, one row per joint, the measured position "
                    "against the commanded target (where the joint was stiff) and the measured torque against "
                    "the torque the MIT command asked for (effort + stiffness x position error + damping x "
                    "velocity error), with the modes shaded.")
    p.add_argument("recording", metavar="FILE.mcap", help="a recording of prime sim, bringup or calibrate")
    p.add_argument("joints", nargs="*", metavar="JOINT", help="joints to draw (default: all 14)")
    p.add_argument("--output", "-o", metavar="FILE.png", type=output_file,
                   help="the picture (default: FILE.png beside the recording)")
    add_config_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from humanoid_prime.config.hardware import load_hardware
    from humanoid_prime.errors import PrimeError
    from humanoid_prime.record.plot import plot_recording
    from humanoid_prime.record.read import read_recording

    output = args.output or Path(args.recording).with_suffix(".png")
    if output.absolute().resolve() == Path(args.recording).absolute().resolve():
        raise PrimeError(f"--output {output} is the recording itself; name another file for the picture")
    recording = read_recording(args.recording, load_hardware(args.hardware).all_joints)
    joints = list(args.joints) or list(recording.names)
    for joint in joints:
        recording.index(joint)  # an unknown joint is one line, before anything is drawn
    if args.output is None and not output.parent.is_dir():
        raise PrimeError(f"cannot write {output}: no such folder")
    plot_recording(recording, joints, output)
    print(f"wrote {output} ({len(joints)} joints, {len(recording.time)} ticks)")
    return 0
