"""The CAN checks: the SocketCAN link (up, bitrate, controller state, error counters, transmit queue), as
``ip -details -statistics -json link show`` reports it, and each Sito wrist of the hardware file heard on it.

A Sito has no read request (``drivers/sito/probe.py``): without ``--op`` the doctor only listens, and a wrist that
nothing has enabled stays silent, so it is reported as not checked. ``--op`` enables each wrist limp for the probe,
unless wrists already stream unprompted: then a program drives the bus, and the probe's disable would stop them.
"""

from __future__ import annotations

import can

from humanoid_prime.config.hardware import HardwareConfig
from humanoid_prime.doctor.report import Check, failed, not_run, passed, warned
from humanoid_prime.doctor.system import Json, ip_link, member, strings
from humanoid_prime.drivers.sito.bus import open_bus
from humanoid_prime.drivers.sito.probe import Heard, listen
from humanoid_prime.errors import PrimeError

GROUP = "can"
LISTEN_S = 0.5  # how long the bus is listened to (with --op: after the limp probe's enable)
FRAMES_PER_WRIST_TICK = 2  # the host's command and its gains, at most, every tick
STATES = {"ERROR-ACTIVE": "pass", "ERROR-WARNING": "warn", "ERROR-PASSIVE": "fail", "BUS-OFF": "fail",
          "STOPPED": "fail", "SLEEPING": "fail"}
LINK_CHECKS = ("link", "bitrate", "state", "errors", "txqueuelen")


def _fix_up(channel: str, bitrate: int) -> str:
    return f"sudo ip link set {channel} down; sudo ip link set {channel} up type can bitrate {bitrate}"


def link_checks(channel: str, bitrate: int, wrists: int, exists: bool, link: Json | None) -> list[Check]:
    """The SocketCAN link of ``channel`` from its ``ip -json`` entry ``link``."""
    if not exists:
        return [failed(GROUP, "link", f"no network interface {channel!r} (buses.can.channel)",
                       "plug the CAN adapter in and load its driver, or set buses.can.channel to one `ip -br link "
                       "type can` lists"),
                *(not_run(GROUP, name, f"no interface {channel!r}") for name in LINK_CHECKS[1:])]
    if link is None:
        return [not_run(GROUP, name, "`ip -details -json link show` gave no answer") for name in LINK_CHECKS]
    info, xstats = member(link, "linkinfo", "info_data"), member(link, "linkinfo", "info_xstats")
    checks = []
    flags = strings(link.get("flags"))
    kind = link.get("link_type")
    if kind != "can":
        return [failed(GROUP, "link", f"{channel} is a {kind or 'non-CAN'} link, not CAN",
                       "set buses.can.channel to the CAN adapter (`ip -br link show type can`)"),
                *(not_run(GROUP, name, f"{channel} is no CAN link") for name in LINK_CHECKS[1:])]
    if "UP" not in flags:
        checks.append(failed(GROUP, "link", f"{channel} is down", _fix_up(channel, bitrate)))
    else:
        checks.append(passed(GROUP, "link", f"{channel} is up"))
    timing = member(info, "bittiming")
    running = timing.get("bitrate")
    if not isinstance(running, int):
        checks.append(not_run(GROUP, "bitrate", f"{channel} reports no bit timing (a virtual CAN link has none)"))
    elif running != bitrate:
        checks.append(failed(GROUP, "bitrate", f"{channel} runs at {running} bit/s; the wrists and "
                                               f"buses.can.bitrate say {bitrate}", _fix_up(channel, bitrate)))
    else:
        point = timing.get("sample_point")
        checks.append(passed(GROUP, "bitrate", f"{channel} at {bitrate} bit/s"
                                               + (f", sample point {point}" if point is not None else "")))
    state = info.get("state")
    checks.append(state_check(channel, state if isinstance(state, str) else None))
    checks.append(errors_check(channel, member(info, "berr_counter"), xstats, member(link, "stats64")))
    checks.append(txqueue_check(channel, link.get("txqlen"), wrists))
    return checks


def state_check(channel: str, state: str | None) -> Check:
    if state is None:
        return not_run(GROUP, "state", f"{channel} reports no controller state (a virtual CAN link has none)")
    verdict = STATES.get(state, "warn")
    if verdict == "pass":
        return passed(GROUP, "state", f"{channel} is {state}")
    text = f"{channel} is {state}" + {
        "ERROR-WARNING": ": its error counters passed 96, frames are being lost or not acknowledged",
        "ERROR-PASSIVE": ": its error counters passed 127, it may no longer flag errors on the bus",
        "BUS-OFF": ": it took itself off the bus after too many errors",
        "STOPPED": ": the controller is stopped"}.get(state, "")
    fix = ("check the termination (120 ohm at each end: about 60 ohm between CAN_H and CAN_L, power off), the "
           "wiring and that every wrist is powered; then restart the link: "
           f"sudo ip link set {channel} down; sudo ip link set {channel} up")
    return failed(GROUP, "state", text, fix) if verdict == "fail" else warned(GROUP, "state", text, fix)


def errors_check(channel: str, berr: Json, xstats: Json, stats: Json) -> Check:
    counts = {"tx error counter": berr.get("tx", 0), "rx error counter": berr.get("rx", 0),
              "bus-off": xstats.get("bus_off", 0), "error-passive": xstats.get("error_passive", 0),
              "restarts": xstats.get("restarts", 0), "bus errors": xstats.get("bus_error", 0),
              "rx errors": member(stats, "rx").get("errors", 0), "tx errors": member(stats, "tx").get("errors", 0)}
    nonzero = {name: value for name, value in counts.items() if isinstance(value, int) and value}
    if not nonzero:
        return passed(GROUP, "errors", f"no error counted on {channel}")
    return warned(GROUP, "errors", f"{channel} counted errors: "
                                   + ", ".join(f"{name} {value}" for name, value in nonzero.items()),
                  "check the termination and wiring (a bus that errs drops wrist frames); the counters restart "
                  f"with the link: sudo ip link set {channel} down; sudo ip link set {channel} up")


def txqueue_check(channel: str, txqueuelen: object, wrists: int) -> Check:
    needed = 2 * FRAMES_PER_WRIST_TICK * wrists  # two ticks of commands and gains
    if not isinstance(txqueuelen, int):
        return not_run(GROUP, "txqueuelen", f"{channel} reports no transmit queue length")
    if txqueuelen < needed:
        return warned(GROUP, "txqueuelen", f"{channel} queues {txqueuelen} frames; {wrists} wrists send up to "
                                           f"{FRAMES_PER_WRIST_TICK * wrists} a tick, so one late tick fills it",
                      f"sudo ip link set {channel} txqueuelen 1000")
    return passed(GROUP, "txqueuelen", f"{channel} queues {txqueuelen} frames")


def wrist_checks(mit_joints: dict[str, int], heard: Heard, *, probed: bool, seconds: float,
                 busy: bool = False) -> list[Check]:
    """One line per wrist of the hardware file: heard, or not, and whether it was probed. ``busy``: the probe was
    asked for but not sent, the wrists already streaming (something drives them; the probe's disable would stop
    them)."""
    checks = []
    how = "to the limp probe" if probed else "unprompted"
    for joint, can_id in mit_joints.items():
        name = f"wrist.{joint}"
        frames = heard.frames.get(can_id)
        if frames:
            counted = ", ".join(f"{count} {kind}" for kind, count in sorted(frames.items()))
            checks.append(passed(GROUP, name, f"id {can_id} answered {how}: {counted} in {seconds:g} s"))
        elif can_id in heard.invalid:
            count, problem = heard.invalid[can_id]
            checks.append(failed(GROUP, name, f"id {can_id} sent {count} frames the Sito protocol refuses ({problem}) "
                                              "and no valid feedback",
                                 "check the wrist's firmware and that no other device uses its id "
                                 "(`prime can monitor` shows each frame)"))
        elif probed:
            checks.append(failed(GROUP, name, f"id {can_id} is silent: no feedback {seconds:g} s after the limp "
                                              "probe enabled it",
                                 f"check the wrist's power and cable; `prime can discover --probe --ids 1-255` finds "
                                 f"it if its id is not {can_id} (joints.mit_joints)"))
        elif busy:
            checks.append(not_run(GROUP, name, f"id {can_id} not heard, and not probed: other wrists stream "
                                               "unprompted, so a program drives this bus and the probe's disable "
                                               "would stop its wrists", "run the doctor with that program stopped"))
        else:
            checks.append(not_run(GROUP, name, f"id {can_id} not heard in {seconds:g} s; a Sito sends only once "
                                               "enabled and has no read request",
                                  "prime doctor --op (enables each wrist limp for the probe: zero gains, zero current, "
                                  "disabled after)"))
    strangers = sorted(set(heard.frames) - set(mit_joints.values()))
    if strangers:
        checks.append(warned(GROUP, "wrist.others", f"ids {', '.join(map(str, strangers))} heard on the bus, not in "
                                                    "joints.mit_joints", "give each wrist its id in joints.mit_joints"))
    return checks


def can_checks(hardware: HardwareConfig, *, interface: str | None = None, channel: str | None = None,
               op: bool = False, seconds: float = LISTEN_S) -> list[Check]:
    """Every CAN check: the link (SocketCAN only) and each wrist."""
    interface = interface or hardware.can.interface
    channel = channel or hardware.can.channel
    wrists = dict(hardware.mit_joints)
    checks: list[Check]
    if interface == "socketcan":
        checks = link_checks(channel, hardware.can.bitrate, len(wrists), *ip_link(channel))
    else:
        checks = [not_run(GROUP, "link", f"the bus is python-can {interface!r} (channel {channel}), not a SocketCAN "
                                         "link: its state, bitrate, error counters and transmit queue are "
                                         "SocketCAN's")]
    if interface == "socketcan" and checks[0].verdict.value == "fail":
        return checks + [not_run(GROUP, f"wrist.{joint}", f"{channel} is not usable") for joint in wrists]
    try:
        bus = open_bus(hardware, interface=interface, channel=channel)
    except PrimeError as exc:
        return checks + [failed(GROUP, "bus", str(exc))]
    try:
        heard = listen(bus, seconds)  # unprompted first: wrists that stream are driven by something already
        probe = op and not heard.frames
        if probe:
            heard = listen(bus, seconds, enable=wrists.values())
    except can.CanError as exc:
        return checks + [failed(GROUP, "bus", f"CAN error on {channel}: {exc}", _fix_up(channel, hardware.can.bitrate))]
    finally:
        bus.shutdown()
    return checks + wrist_checks(wrists, heard, probed=probe, seconds=seconds, busy=op and not probe)
