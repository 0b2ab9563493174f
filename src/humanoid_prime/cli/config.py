"""``prime config init|show``: the robot's own configuration folder, and which file each command reads."""

from __future__ import annotations

import argparse
import os

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import add_config_options, add_json_option, print_json
from humanoid_prime.config.location import FILE_NAMES, KINDS, robot_folder, template
from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_bytes


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("config", help=summary("config"),
                              description="Every command reads the robot's hardware, calibration and controllers "
                                          "files by one rule: the file given with --hardware, --calibration or "
                                          "--controllers; else the one in the robot's config folder "
                                          "($PRIME_CONFIG_DIR, else $XDG_CONFIG_HOME/prime, i.e. ~/.config/prime; "
                                          "with --robot NAME or $PRIME_ROBOT, its NAME subfolder); else the "
                                          "bundled template, which no command ever writes.")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    init = actions.add_parser("init", help="copy the bundled templates into the robot's config folder",
                              description="Create the robot's config folder with a copy of each bundled template "
                                          "(hardware, calibration, controllers). A file already there is kept as "
                                          "it is.")
    init.add_argument("--robot", metavar="NAME",
                      help="the robot's config subfolder, for labs with several Primes (default: $PRIME_ROBOT)")
    add_json_option(init)
    init.set_defaults(func=_init, makes_config=True)
    show = actions.add_parser("show", help="which configuration file every command would use, and why",
                              description="Print the hardware, calibration and controllers files the commands "
                                          "would read with these options and this environment, where each comes "
                                          "from, and its sha256.")
    add_config_options(show, calibration=True, controllers=True)
    add_json_option(show)
    show.set_defaults(func=_show)


def _init(args: argparse.Namespace) -> int:
    folder = robot_folder(args.robot)
    if os.path.lexists(folder.path) and not folder.path.is_dir():
        raise PrimeError(f"{folder.path} is not a folder; move it away and run this again")
    kept = {kind: folder.own_file(kind) is not None for kind in KINDS}  # all three checked before one is written
    rows = []
    for kind in KINDS:
        path = folder.path / FILE_NAMES[kind]
        if not kept[kind]:
            atomic_write_bytes(path, template(kind).read_bytes())
        rows.append({"kind": kind, "path": str(path), "action": "kept" if kept[kind] else "written"})
    if args.json:
        print_json({"folder": str(folder.path), "source": folder.why, "files": rows})
        return 0
    print(f"{folder.path} ({folder.why}):")
    for row in rows:
        print(f"  {row['action']:<8} {row['path']}")
    print("Edit prime_hardware.yaml for this robot's buses, then calibrate it: prime calibrate"
          + (f" --robot {folder.robot}" if folder.robot else ""))
    return 0


def _show(args: argparse.Namespace) -> int:
    files = args.config
    if args.json:
        print_json({"folder": str(files.folder.path), "folder_source": files.folder.why,
                    "folder_exists": files.folder.path.is_dir(), **files.as_dict()})
        return 0
    exists = "" if files.folder.path.is_dir() else f" (does not exist yet; `{files.folder.init_command()}`)"
    print(f"robot config folder: {files.folder.path}, from {files.folder.why}{exists}")
    for c in files:
        print(f"  {c.kind:<11} {c.path}")
        print(f"  {'':<11} from {c.why}; sha256 {c.sha256()}")
    if files.calibration.template:
        print("The calibration is the bundled identity template: on the real robot, modes that move a joint are "
              "refused until the robot is calibrated (prime calibrate), or run with --uncalibrated.")
    return 0
