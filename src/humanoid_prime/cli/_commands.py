"""The subcommands: which module defines each, and the line ``prime --help`` shows for it. ``prime COMMAND``
imports only that command's module, so the command line answers without loading what other commands need."""

from __future__ import annotations

# command -> (module of humanoid_prime.cli that registers it, its line in `prime --help`)
COMMANDS: dict[str, tuple[str, str]] = {
    "bench": ("bench", "measure the performance targets"),
    "bringup": ("bringup", "bring up Prime on both buses (or one) and run the controller manager"),
    "calibrate": ("calibrate", "calibrate the robot: find each joint's stops and write its calibration file"),
    "calibration": ("calibration", "fold, flip or check a calibration file"),
    "can": ("can", "monitor, discover or emulate the Sito wrists on CAN"),
    "config": ("config", "the robot's configuration folder: create it, show what is used"),
    "decode": ("decode", "decode a statusword, eRob error code or EtherCAT AL status"),
    "doctor": ("doctor", "check the host, the buses and the robot before anything moves; the fix for each finding"),
    "ec": ("ec", "EtherCAT commissioning: scan the ring, read and write SDOs"),
    "emulate": ("emulate", "emulate hardware for running the stack without the robot"),
    "gains": ("gains", "eRob registers (vel_reg, pos_reg, integral) for --kp/--kd or --mode"),
    "info": ("info", "joint topology: family, bus, address, limits, direction"),
    "limp": ("limp", "damped limp of one eRob (position gain 0, damping kept) until Enter"),
    "plot": ("plot", "plot commanded vs measured position and torque per joint from a recording (.mcap) to a PNG"),
    "remote": ("remote", "stream MIT commands to a running Prime over DDS (REMOTE mode) and show what it publishes"),
    "replay": ("view", "play a recording (.mcap) into the 3D view"),
    "reset": ("reset", "reset latched drive faults of a running prime"),
    "sim": ("sim", "run the simulated Prime through every mode (MuJoCo, headless by default)"),
    "switch": ("switch", "switch the mode of a running prime sim or bringup"),
    "view": ("view", "the live 3D view of a running prime sim or prime bringup, in the browser"),
}


def summary(command: str) -> str:
    """The line ``prime --help`` shows for ``command``."""
    return COMMANDS[command][1]
