"""The faults the soak injects, in turn, on both buses, each with what the stack must do about it (``expect``):

- ``counted``: absorbed without a flag (one lost or garbage frame), and visible in a counter;
- ``recovered``: flagged under ``flag``, then cleared by the stack itself;
- ``latched``: flagged, held until the operator's reset (which the soak sends once the ring is whole), then
  cleared (a drive fault, and a drive whose slave was lost and came back: it stays disabled until the operator
  says so);
- ``refused``: an SDO the drive aborts reaches its caller as that abort, and nothing else changes.

Each is injected through the virtual Prime's control channel (``RingControl``) or the run's own session.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from humanoid_prime.drivers.erob.objects import RATED_TORQUE
from humanoid_prime.drivers.ethercat.errors import SdoError
from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.session import Session
from humanoid_prime.virtual.ring.control import RingControl

SETTLE_S = 3.0  # how long after an injection (or its end) the stack has to flag and recover
LOST_RING = 9  # the last slave: losing it leaves the rest of the line reachable
REFERENCE_RING = 0  # the first slave, the reference clock: losing it cuts the whole line off
VERIFY_READS = 3  # reads of the returned drive's settings, when a mode switch falls between two

Inject = Callable[[RingControl, Session], object]  # the injection; what it returns, a string, is its detail
End = Callable[[RingControl], object]  # undoes a fault that lasts ``hold_s``
Verify = Callable[[RingControl, Session], str | None]  # after the reset: what is wrong with the drive released


@dataclass
class Fault:
    """One fault: where it goes, what the stack must do about it and the flags that may say so, how it is
    injected and, where it lasts, ended."""

    name: str
    bus: str
    expect: str  # counted, recovered, latched, refused
    flag: str | None  # fnmatch pattern of the flag key it raises (None: it must raise none)
    inject: Inject  # what happened: a string is the injection's detail
    hold_s: float = 0.0  # how long the fault lasts before ``end`` undoes it
    end: End | None = None
    # after the operator's reset of a latched fault: what is wrong with the drive it released (None: nothing)
    verify: Verify | None = None
    also: tuple[str, ...] = ()  # flags it may raise besides ``flag`` (consequences, not surprises)
    settle_s: float = SETTLE_S  # how long after it ended the stack has to flag (and, latched, be reset)

    @property
    def patterns(self) -> tuple[str, ...]:
        """Every flag key pattern it may raise: its own, then its consequences."""
        return (*((self.flag,) if self.flag else ()), *self.also)


def _sito(joint: str, **fields: object) -> End:
    """One wrist's fault setting through the control channel: a fault's end, or (``_on_control``) its injection."""
    return lambda control: control.call("sito", joint=joint, **fields)


def _on_control(end: End) -> Inject:
    """An injection that needs only the virtual Prime's control channel."""
    return lambda control, _session: end(control)


def _sdo_abort(_control: RingControl, session: Session) -> str:
    """Write the read-only rated torque (0x6076) of ring 0, as a mistyped `prime ec sdo` would."""
    master = session.ethercat.master if session.ethercat is not None else None
    if master is None:
        raise PrimeError("the soak's SDO abort needs the run's EtherCAT master")
    try:
        master.sdo_write(0, RATED_TORQUE, 0, b"\x00\x00\x00\x00")
    except SdoError as exc:
        return str(exc)
    raise PrimeError("the drive accepted a write to its read-only 0x6076")


def _settings_restored(ring: int) -> Verify:
    """The check that the drive at ``ring``, returned, holds the gate and the gains of the mode the impedance
    manager applied last: a drive that lost power comes back on factory gains, and must not be enabled on them."""

    def verify(control: RingControl, session: Session) -> str | None:
        impedance = session.impedance
        if impedance is None or impedance.mode is None:  # no impedance manager, or no mode's gains applied yet
            return None
        for _ in range(VERIFY_READS):  # a mode switch between the two reads: read again
            impedance.wait_idle(5.0)
            mode, switches = impedance.mode, len(impedance.reports)
            drive = control.slave(ring)["drive"]
            want = impedance.targets[mode][ring]
            held = (drive["gate"], drive["pos_reg"], drive["vel_reg"], drive["integral"])
            if held == (1, want.pos_reg, want.vel_reg, want.integral):
                return None
            if len(impedance.reports) == switches:
                break
        return (f"ring {ring} was released with gate {held[0]} and registers {held[1:]}, not the gate 1 and "
                f"{mode.value}'s {(want.pos_reg, want.vel_reg, want.integral)}")

    return verify


FAULTS: tuple[Fault, ...] = (
    Fault("one EtherCAT frame lost", "ethercat", "counted", None,
          lambda c, s: c.call("drop", count=1, where="request")),
    Fault("EtherCAT replies lost, 20 frames", "ethercat", "recovered", "*/ethercat/wkc",
          lambda c, s: c.call("drop", count=20, where="reply"),
          also=("*/ethercat/ring*/lost",)),  # the supervision's state reads are lost too: "not answering"
    Fault("EtherCAT frames delayed 30 ms, 30 frames", "ethercat", "recovered", "*/ethercat/wkc",
          lambda c, s: c.call("delay", seconds=0.03, count=30), also=("*/ethercat/ring*/lost",)),
    Fault("garbage EtherCAT frames", "ethercat", "counted", None, lambda c, s: c.call("garbage", count=5)),
    # a slow drive or a busy host: mailbox replies 40 ms late, the frames that carry replies back after the 2 ms a
    # frame is given, and the whole emulator stalled for 30 ms (the cycle's frames late too)
    Fault("EtherCAT mailbox replies 40 ms late, 20 replies", "ethercat", "counted", None,
          lambda c, s: c.call("late_replies", count=20, seconds=0.04)),
    Fault("EtherCAT reply frames held 8 ms, 5 frames", "ethercat", "counted", None,
          lambda c, s: c.call("hold_reply_frames", count=5, seconds=0.008)),
    Fault("EtherCAT ring stalled 30 ms", "ethercat", "counted", None, lambda c, s: c.call("stall", seconds=0.03)),
    # back in OP once it has relocked (350 frames at the control rate: 7 s at 50 Hz), its drive held disabled
    Fault("slave lost and returned", "ethercat", "latched", f"*/ethercat/ring{LOST_RING}/disabled",
          lambda c, s: c.call("lose", position=LOST_RING), hold_s=1.0,
          end=lambda c: c.call("restore", position=LOST_RING), settle_s=15.0, verify=_settings_restored(LOST_RING),
          also=(f"*/ethercat/ring{LOST_RING}/lost", "*/ethercat/wkc",
                "*/erob/impedance/ring*")),  # a mode switch meanwhile is refused, and flagged
    # the first slave: the ring's time (the reference clock) restarts from 0 with it, and the line behind it is cut
    # meanwhile, so every other drive's watchdog runs out (0xA000, latched too); its clock is set to the time of a
    # drive that kept its own before SYNC0 starts again, and the others relock on it
    Fault("reference clock slave lost and returned", "ethercat", "latched", f"*/ethercat/ring{REFERENCE_RING}/disabled",
          lambda c, s: c.call("lose", position=REFERENCE_RING), hold_s=1.0,
          end=lambda c: c.call("restore", position=REFERENCE_RING), settle_s=20.0,
          verify=_settings_restored(REFERENCE_RING),
          also=("*/ethercat/ring*/lost", "*/ethercat/wkc", "*/ethercat/ring*/fault", "*/ethercat/ring*/disabled",
                "*/erob/impedance/ring*")),
    Fault("drive fault 0x7500", "ethercat", "latched", "*/ethercat/ring6/fault",
          lambda c, s: c.call("fault", position=6, code=0x7500)),
    Fault("SDO abort", "ethercat", "refused", None, _sdo_abort),
    Fault("silent Sito", "can", "recovered", "*/rx_timeout/*", _on_control(_sito("left_wrist_roll", silent=True)),
          hold_s=1.0, end=_sito("left_wrist_roll", silent=False)),
    Fault("garbage CAN frames", "can", "recovered", "*/invalid_frame",
          _on_control(_sito("right_wrist_roll", garbage=True)), hold_s=1.0,
          end=_sito("right_wrist_roll", garbage=False)),
    Fault("Sito frames dropped (30 %)", "can", "counted", None,
          _on_control(_sito("right_wrist_pitch", drop_fraction=0.3)), hold_s=2.0,
          end=_sito("right_wrist_pitch", drop_fraction=0.0)),
    Fault("Sito feedback 50 ms late", "can", "counted", None, _on_control(_sito("left_wrist_pitch", late_s=0.05)),
          hold_s=2.0,
          end=_sito("left_wrist_pitch", late_s=0.0)),
)
