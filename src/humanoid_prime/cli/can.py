"""``prime can monitor`` / ``discover`` look at the Sito wrists' CAN traffic; ``prime can emulate`` answers
as the four wrists would, for running the stack without the robot (e.g. over udp_multicast).

Monitor and discover are read-only by default. ``discover --probe`` enables feedback on the probed ids
with zero gains (limp) and disables them again on every exit path.
"""

from __future__ import annotations

import argparse
import sys
import time

import can

from humanoid_prime.cli._commands import summary
from humanoid_prime.cli._common import (
    add_config_options,
    add_duration_option,
    add_json_option,
    output_file,
    print_json,
    whole,
    write_summary,
)
from humanoid_prime.config.hardware import HardwareConfig, load_hardware
from humanoid_prime.config.robot import load_robot
from humanoid_prime.drivers.sito.bus import CAN_ERR_ACK, CAN_ERR_BUSOFF, CAN_ERR_CRTL, CAN_ERR_RESTARTED, open_bus
from humanoid_prime.drivers.sito.probe import listen
from humanoid_prime.drivers.sito.protocol import (
    MODE_MIT,
    SITO_MODELS,
    Command,
    Disable,
    Enable,
    Feedback1,
    Feedback2,
    Frame,
    Gains,
    InvalidFrame,
    SitoModel,
    UndecodedFeedback,
    counts_to_position,
    counts_to_velocity,
    current_mA_to_torque,
    firmware_to_kd,
    firmware_to_kp,
    parse,
    sito_model,
    split_arbitration_id,
)
from humanoid_prime.errors import PrimeError
from humanoid_prime.virtual.plant import InertiaPlant
from humanoid_prime.virtual.sito import SitoEmulator

_ERROR_CLASSES = ((CAN_ERR_BUSOFF, "bus-off"), (CAN_ERR_ACK, "no acknowledge"),
                  (CAN_ERR_CRTL, "controller problem"), (CAN_ERR_RESTARTED, "controller restarted"))


def describe(msg: can.Message, model: SitoModel, joints: dict[int, str]) -> str:
    """One line for a frame: Sito frames decoded with raw counts and SI values (motor frame, uncalibrated)."""
    if msg.is_error_frame:
        kinds = [text for bit, text in _ERROR_CLASSES if msg.arbitration_id & bit] or ["other"]
        return f"error frame: {', '.join(kinds)} (class 0x{msg.arbitration_id:03X})"
    raw = bytes(msg.data[:msg.dlc]).hex(" ")
    split = split_arbitration_id(msg.arbitration_id) if msg.is_extended_id else None
    if split is None:
        return f"foreign id 0x{msg.arbitration_id:X} dlc {msg.dlc}: {raw}"
    can_id, frame_type = split
    who = f"id {can_id:3d} {joints.get(can_id, '(not configured)'):<18s}"
    try:
        frame = _parse(frame_type, msg)
    except InvalidFrame as exc:
        return f"{who} INVALID type 0x{frame_type:02X} ({exc}): {raw}"
    match frame:
        case Disable():
            text = "disable (reset)"
        case Enable(mode, (fb1, fb2, fb3)):
            mode_text = "MIT" if mode == MODE_MIT else "not MIT"
            text = f"enable mode 0x{mode:02X} ({mode_text}), feedback every {fb1}/{fb2}/{fb3} ms (0 = off)"
        case Command(current, velocity, position):
            text = (f"command pos {position} ({counts_to_position(position):+.4f} rad) "
                    f"vel {velocity} ({counts_to_velocity(velocity):+.4f} rad/s) "
                    f"ff {current} mA ({current_mA_to_torque(current, model):+.3f} Nm)")
        case Gains(kp_fw, kd_fw):
            text = (f"gains Kp {kp_fw:.6g} ({firmware_to_kp(kp_fw, model):.3f} Nm/rad) "
                    f"Kd {kd_fw:.6g} ({firmware_to_kd(kd_fw, model):.3f} Nm·s/rad)")
        case Feedback1(voltage, pwm, current, velocity):
            # Sources disagree on where the phase current sits (protocol.FEEDBACK1): both readings, so a
            # motor under a known load shows which is right.
            text = (f"feedback-1 voltage {voltage} current(4-5) {current} mA "
                    f"({current_mA_to_torque(current, model):+.3f} Nm) current(2-3) {pwm} mA "
                    f"({current_mA_to_torque(pwm, model):+.3f} Nm) "
                    f"vel {velocity} ({counts_to_velocity(velocity):+.4f} rad/s)")
        case Feedback2(motor, output):
            text = f"feedback-2 motor {motor} output {output} ({counts_to_position(output):+.4f} rad)"
        case UndecodedFeedback(kind, payload):
            text = f"feedback 0x{kind:02X} (layout undocumented, ignored by the driver): {payload.hex(' ')}"
    return f"{who} {text}"


def _parse(frame_type: int, msg: can.Message) -> Frame:
    """The Sito frame ``msg`` carries (its id in the Sito range); InvalidFrame as the protocol judges it."""
    return parse(frame_type, bytes(msg.data[:msg.dlc]), remote=msg.is_remote_frame, fd=msg.is_fd)


def _ids(text: str) -> list[int]:
    """``22,23,38-39`` -> [22, 23, 38, 39]."""
    ids: list[int] = []
    try:
        for part in text.split(","):
            low, dash, high = part.strip().partition("-")
            if dash and not high:
                raise ValueError(part)
            ids.extend(range(int(low), int(high or low) + 1))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a list of CAN ids such as 22,23,38-39") from None
    if not ids or any(not 1 <= i <= 255 for i in ids):
        raise argparse.ArgumentTypeError(f"{text!r}: CAN ids are 1..255")
    return sorted(set(ids))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("can", help=summary("can"),
                              description="Look at the Sito wrists' CAN traffic, or emulate the wrists.")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)

    def bus_options(sub: argparse.ArgumentParser) -> None:
        add_config_options(sub)
        sub.add_argument("--interface", help="python-can interface (default: buses.can.interface)")
        sub.add_argument("--channel", help="CAN channel (default: buses.can.channel)")
        sub.add_argument("--model", default="TA40-50", choices=sorted(SITO_MODELS), help="Sito model (default TA40-50)")

    m = actions.add_parser("monitor", help="decode live Sito traffic",
                           description="Print every frame on the bus, Sito frames decoded (raw motor frame, "
                                       "no calibration). Read-only. Stops after --count frames, --duration, "
                                       "or Ctrl-C.")
    bus_options(m)
    add_duration_option(m, "stop after this long")
    m.add_argument("--count", type=whole(at_least=1), help="stop after this many frames")
    _summary_option(m)
    m.set_defaults(func=_monitor)

    d = actions.add_parser("discover", help="list the Sito CAN ids heard",
                           description="Listen and list the Sito ids heard. Read-only unless --probe, which "
                                       "enables feedback with zero gains (limp) and disables again.")
    bus_options(d)
    add_duration_option(d, "how long to listen (default 1 s)", default=1.0)
    d.add_argument("--probe", action="store_true",
                   help="enable feedback (zero gains) on the probed ids, listen, then disable them")
    d.add_argument("--ids", type=_ids, help="ids to probe, e.g. 22,23,38-39 (default: joints.mit_joints)")
    add_json_option(d)
    d.set_defaults(func=_discover)

    e = actions.add_parser("emulate", help="answer as the Sito wrists would (no robot needed)",
                           description="Emulated Sito motors for every joints.mit_joints entry, each on a "
                                       "link with inertia, gravity and friction, running the MIT law at 1 kHz. "
                                       "Use a virtual interface, e.g. --interface udp_multicast --channel "
                                       "239.74.163.2, or a vcan channel; never the robot's bus. Stops after --duration "
                                       "or Ctrl-C.")
    bus_options(e)
    add_duration_option(e, "stop after this long")
    _summary_option(e)
    e.set_defaults(func=_emulate)


def _summary_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--summary", metavar="FILE", type=output_file, help="write the run's figures as JSON")


def _open(args: argparse.Namespace) -> tuple[HardwareConfig, can.BusABC, SitoModel]:
    """The hardware file, the bus, the Sito model; the bus last, so nothing can fail between it and the caller's
    ``finally: bus.shutdown()``."""
    hardware, model = load_hardware(args.hardware), sito_model(args.model)
    return hardware, open_bus(hardware, interface=args.interface, channel=args.channel), model


def _emulate(args: argparse.Namespace) -> int:
    robot = load_robot(args.hardware)
    interface = args.interface or robot.hardware.can.interface
    channel = args.channel or robot.hardware.can.channel
    if interface == "socketcan" and not channel.startswith("vcan"):
        raise PrimeError(f"refusing to emulate wrists on SocketCAN channel {channel!r}, where real ones may live; "
                         "use a vcan channel or a virtual interface, e.g. --interface udp_multicast")
    plant = InertiaPlant.wrists(len(robot.hardware.sito_joints), gravity=0.3, coulomb=0.02)
    with open_bus(robot.hardware, interface=args.interface, channel=args.channel) as bus:  # shut down on every path
        emulator = SitoEmulator.for_robot(robot, bus, plant, model=args.model)
        ids = ", ".join(str(i) for i in emulator.motors)
        # python-can's virtual bus lives in one process: another command cannot hear these wrists.
        reach = (": heard only inside this process; for another command use --interface udp_multicast --channel "
                 "239.74.163.2, or a vcan channel" if interface == "virtual" else "")
        print(f"emulating Sito {args.model} ids {ids} on {channel} ({interface}){reach}", flush=True)
        deadline = time.monotonic() + args.duration if args.duration else float("inf")
        emulator.start()
        try:
            while time.monotonic() < deadline:
                time.sleep(min(0.1, max(0.0, deadline - time.monotonic())))
        except KeyboardInterrupt:
            pass
        finally:
            emulator.stop()
    enabled = [str(i) for i, m in emulator.motors.items() if m.enabled]
    write_summary(args, {"interface": interface, "channel": channel, "ids": list(emulator.motors),
                         "seconds": round(emulator.time, 3), "enabled_at_end": [int(i) for i in enabled],
                         "frames_sent": emulator.frames_sent, "frames_received": emulator.frames_received,
                         "not_can_frames": emulator.foreign_received})
    print(f"stopped after {emulator.time:.1f} s; enabled at the end: {', '.join(enabled) or 'none'}")
    return 0


def _joint_names(hardware: HardwareConfig) -> dict[int, str]:
    return {can_id: joint for joint, can_id in hardware.mit_joints.items()}


def _monitor(args: argparse.Namespace) -> int:
    hardware, bus, model = _open(args)
    joints = _joint_names(hardware)
    start = time.monotonic()
    deadline = start + args.duration if args.duration else float("inf")
    seen = not_can = 0
    try:
        while time.monotonic() < deadline and (args.count is None or seen < args.count):
            try:
                msg = bus.recv(min(0.1, max(0.0, deadline - time.monotonic())))
            except can.CanOperationError as exc:  # a datagram that is no CAN frame (udp_multicast): shown, not fatal
                print(f"{time.monotonic() - start:10.4f}  not a CAN frame: {exc}", flush=True)
                not_can += 1
                continue
            if msg is None:
                continue
            seen += 1
            print(f"{time.monotonic() - start:10.4f}  {describe(msg, model, joints)}", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        bus.shutdown()
    write_summary(args, {"channel": args.channel or hardware.can.channel, "frames": seen, "not_can_frames": not_can,
                         "seconds": round(time.monotonic() - start, 3)})
    return 0


def _discover(args: argparse.Namespace) -> int:
    hardware, bus, model = _open(args)
    joints = _joint_names(hardware)
    probed = (args.ids or sorted(joints)) if args.probe else []
    try:
        listened = listen(bus, args.duration, enable=probed)
    except can.CanError as exc:
        raise PrimeError(f"CAN error on {args.channel or hardware.can.channel}: {exc}; check that the interface "
                         "is up") from None
    finally:
        bus.shutdown()
    heard, invalid = listened.frames, listened.invalid
    missing = [i for i in (probed or sorted(joints)) if i not in heard]
    result = {
        "channel": args.channel or hardware.can.channel,
        "probed": probed,
        "heard": [{"can_id": i, "joint": joints.get(i), "frames": dict(heard[i])} for i in sorted(heard)],
        "not_heard": [{"can_id": i, "joint": joints.get(i)} for i in missing],
        "invalid": [{"can_id": i, "joint": joints.get(i), "frames": invalid[i][0], "problem": invalid[i][1]}
                    for i in sorted(invalid)],
    }
    if args.json:
        print_json(result)
    else:
        for entry in result["heard"]:
            frames = ", ".join(f"{k} x{v}" for k, v in sorted(entry["frames"].items()))
            joint = entry["joint"] or f"not in {hardware.path.name}"
            print(f"CAN id {entry['can_id']:3d} (0x{entry['can_id']:02X})  {joint:<18s}  {frames}")
        for entry in result["invalid"]:
            joint = entry["joint"] or f"not in {hardware.path.name}"
            print(f"CAN id {entry['can_id']:3d} (0x{entry['can_id']:02X})  {joint:<18s}  INVALID x{entry['frames']} "
                  f"({entry['problem']}): not counted as feedback")
        if missing:
            names = ", ".join(f"{i} ({joints.get(i, 'unconfigured')})" for i in missing)
            print(f"not heard: {names}")
        if not heard and not probed:
            print("no Sito feedback heard; a Sito streams only after enable, so run with --probe to enable "
                  "feedback briefly (zero gains, limp)")
    if missing:
        print(f"prime can discover: {len(missing)} of {len(probed or joints)} wrists not heard "
              f"({', '.join(str(i) for i in missing)})", file=sys.stderr)
    return 1 if missing else 0
