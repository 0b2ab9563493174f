"""``prime limp RING_POS [DAMPING]``: damped limp of one eRob while the others hold, for a hand sweep."""

from __future__ import annotations

import argparse
import signal
import sys
import time
from types import FrameType

from humanoid_prime.calibration.journal import OverrideJournal
from humanoid_prime.calibration.limp import DampedLimp, restore_left
from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import (
    add_config_options,
    add_duration_option,
    add_json_option,
    add_socket_option,
    output_file,
    print_json,
    real,
    whole,
    write_summary,
)
from humanoid_prime.config.hardware import load_hardware
from humanoid_prime.drivers.erob.gains import gains_to_registers, registers_to_gains
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient
from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.socket import SocketSdoClient


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "limp", help=summary("limp"),
        description="Make one eRob damped-limp for a hand sweep: snapshot its gains, arm the gate, position "
                    "gain 0, integral 0, keep (or set) the damping, read back Kp = 0, wait, and restore the "
                    "snapshot on every exit path. The other joints keep holding. Needs a running "
                    "`prime calibrate` or `prime bringup` (or --backend igh where an IgH master runs).")
    p.add_argument("ring_position", type=whole(at_least=0), metavar="RING_POS",
                   help="EtherCAT ring position of the eRob")
    p.add_argument("damping", type=real(above=0.0), nargs="?", metavar="DAMPING",
                   help="damping during the limp in Nm*s/rad (default: keep the drive's velocity gain)")
    add_config_options(p)
    p.add_argument("--backend", choices=("socket", "igh"), default="socket",
                   help="socket: through the running prime process (default); igh: the `ethercat` tool")
    add_socket_option(p)
    add_duration_option(p, "stay limp for S seconds instead of waiting for Enter (scripted sweeps)", zero=True)
    p.add_argument("--summary", metavar="FILE", type=output_file, help="write what was set and restored as JSON")
    add_json_option(p)
    p.set_defaults(func=run)


def _sdo(args: argparse.Namespace) -> SdoClient:
    if args.backend == "igh":
        from humanoid_prime.drivers.ethercat.igh import IghSdo

        return IghSdo()
    return SocketSdoClient(args.socket)


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    hardware = load_hardware(args.hardware)
    joints = {pos: joint for joint, pos in hardware.erob_slaves.items()}
    joint = joints.get(args.ring_position)
    if joint is None:
        known = ", ".join(str(p) for p in sorted(joints))
        raise PrimeError(f"ring position {args.ring_position} is not an eRob in {hardware.path.name} (known: {known})")
    kt, gear = hardware.erob_kt[joint], hardware.erob_gear[joint]
    vel_reg = None
    if args.damping is not None:
        try:
            vel_reg = gains_to_registers(0.0, args.damping, kt=kt, gear=gear,
                                         efficiency=hardware.erob_torque_efficiency[joint]).vel_reg
        except ValueError as exc:
            raise PrimeError(f"DAMPING {args.damping:g} Nm*s/rad cannot be set on {joint}: {exc}") from None
    sdo = _sdo(args)
    marker = sdo if isinstance(sdo, SocketSdoClient) else None
    journal = OverrideJournal(args.config.folder.state, f"socket {marker.path.absolute()}" if marker else "igh",
                              f"prime limp {args.ring_position}")
    for position, line in restore_left(sdo, journal):  # a limp killed before it could restore
        print(line, file=sys.stderr, flush=True)
        if marker is not None:
            marker.mark_limp(position, False)  # restored: the run holds it again
    previous = {sig: signal.signal(sig, _raise_interrupt) for sig in (signal.SIGTERM, signal.SIGHUP)}
    limp = DampedLimp(sdo, args.ring_position, vel_reg, journal=(journal, joint))
    interrupted = False
    marked = False
    try:
        if marker is not None:
            marker.mark_limp(args.ring_position, True)  # the target follows the joint while it is limp
            marked = True
        with limp:
            back = limp.readback
            assert back is not None
            _, kd = registers_to_gains(back.registers, kt=kt, gear=gear)
            if not args.json:
                print(f"{joint} (ring {args.ring_position}) is damped-limp: read back gate={back.gate} "
                      f"Kp(pos_reg)={back.registers.pos_reg} vel_reg={back.registers.vel_reg} "
                      f"(kd ~ {kd:.2f} Nm*s/rad nominal)", flush=True)
            if args.duration is not None:
                time.sleep(max(0.0, args.duration))
            else:
                print("Sweep it firmly to both mechanical stops, return near neutral, then press Enter "
                      "to re-hold (Ctrl-C also restores).", flush=True)
                sys.stdin.readline()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        try:
            if marked and not limp.unrestored:
                marker.mark_limp(args.ring_position, False)  # restored: hold where it is now
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    snap = limp.snapshot
    if snap is None:
        print(f"{joint} (ring {args.ring_position}): interrupted before anything was changed", file=sys.stderr)
        return 130
    restored = {"gate": snap.gate, "pos_reg": snap.registers.pos_reg, "vel_reg": snap.registers.vel_reg,
                "integral": snap.registers.integral}
    back = limp.readback
    report = {"joint": joint, "ring_position": args.ring_position,
              "limp": None if back is None else {"gate": back.gate, **back.registers.__dict__},
              "restored": restored, "interrupted": interrupted}
    write_summary(args, report)
    if args.json:
        print_json(report)
    else:
        print(f"{joint} (ring {args.ring_position}) restored: " + " ".join(f"{k}={v}" for k, v in restored.items()))
    return 130 if interrupted else 0
