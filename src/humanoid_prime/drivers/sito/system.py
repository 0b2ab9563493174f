"""``SitoSystem``: the four Sito wrists on CAN as one hardware component.

A python-can Notifier thread keeps the latest feedback per motor; ``read`` and ``write`` only copy
preallocated arrays and hand ready frames to the bus without waiting. Activation sends zero gains
(limp), then enable with feedback at the bus cycle, and waits for the first feedback from every motor.
Deactivation, interpreter exit and SIGINT/SIGTERM disable every motor.

The bus cycle (``bus.bus_cycle``) is the control period while the wrists' frames fit it, up to about 300 Hz:
a command to each wrist and its two feedback frames take 1.6 to 1.9 ms of a 1 Mbit/s bus. At faster control
rates the commands go out every ``io_every``-th tick and the feedback streams at that cycle (every 4th tick,
4 ms, at 1 kHz), as a hardware component may run slower than its controller manager; ``read`` still gives every
tick the latest feedback. Sending every tick would need 160 to 190 % of the bus at 1 kHz: the transmit queue
would fill and frames would be lost.

Transport health is rebuilt every tick as safety flags (keys ``<channel>/<problem>[/<CAN id>]``):
bus off and interface down stay until re-activation; RX timeout, TX queue overrun, invalid frames
and clamped commands clear as soon as the problem is gone.

Silence is counted from the first ``read`` after activation on, not from the feedback heard during it: the
start-up stages between the two (the ring's bring-up, the policies' sessions) can hold the interpreter for
longer than the RX timeout, and frames the wrists sent meanwhile are not stored until the receive thread runs
again. Judged from activation, every wrist would time out at the first tick and clear at the next.
"""

from __future__ import annotations

import atexit
import contextlib
import math
import os
import signal
import threading
import time
import types
from collections.abc import Callable

import can
import numpy as np
import numpy.typing as npt

from humanoid_prime.config.calibration import Calibration
from humanoid_prime.config.description import SITO_BLOCK
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import Level
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.interfaces import COMMAND_NAMES, CommandArrays, StateArrays
from humanoid_prime.drivers.sito._tick import INVALID, SitoTick
from humanoid_prime.drivers.sito.bus import CAN_ERR_BUSOFF, bus_cycle, is_interface_down, open_bus
from humanoid_prime.drivers.sito.protocol import (
    DATA_LENGTH,
    DISABLE_PAYLOAD,
    ENABLE,
    FEEDBACK1,
    FEEDBACK2,
    HOST_FRAME_TYPES,
    HOST_PAYLOADS,
    ID_PREFIX,
    ID_PREFIX_MASK,
    MIT_FIELDS,
    MODE_MIT,
    UNDECODED_FEEDBACK_TYPES,
    FrameType,
    SitoModel,
    arbitration_id,
    field_range,
    framing_problem,
    sito_model,
    wire_scales,
)
from humanoid_prime.errors import ConfigError, PrimeError

_HOST_TYPES = frozenset(int(t) for t in HOST_FRAME_TYPES)
_FEEDBACK1 = int(FrameType.FEEDBACK1)
_FEEDBACK2 = int(FrameType.FEEDBACK2)
_UNDECODED = frozenset(int(t) for t in UNDECODED_FEEDBACK_TYPES)
_LIFECYCLE_SEND_TIMEOUT_S = 0.02  # gains, enable, disable may wait for queue space; per-tick frames never do
_NOTIFIER_POLL_S = 0.05  # how long stop() can wait for the receive thread
_UNITS = ("rad", "rad/s", "Nm", "Nm/rad", "Nm*s/rad")  # of each command interface


class _FeedbackReceiver(can.Listener):
    """Runs in the Notifier thread: keeps the latest valid feedback of each motor and notes bus trouble."""

    def __init__(self, can_ids: tuple[int, ...], clock: Callable[[], float]) -> None:
        self._slot = [-1] * 256
        for slot, can_id in enumerate(can_ids):
            self._slot[can_id] = slot
        self._clock = clock
        self.lock = threading.Lock()
        n = len(can_ids)
        self.raw = np.zeros((3, n))  # output position counts, velocity counts/s, phase current mA
        self.stamp = np.full((2, n), -np.inf)  # clock() of the last 0xB1 and 0xB2 per motor
        self.frames = 0  # every frame seen, ever
        self.reset()

    def reset(self) -> None:
        with self.lock:
            self.raw[:] = 0.0
            self.stamp[:] = -np.inf
        self.invalid_frames = 0
        self.undecoded_frames = 0  # 0xB0/0xB3 feedback: a Sito may send it; counted and ignored
        self.last_invalid_stamp = -np.inf
        self.last_invalid = ""
        self.bus_off = False
        self.down_error = ""

    def on_message_received(self, msg: can.Message) -> None:
        try:
            self._take(msg)
        finally:
            self.frames += 1  # counted once stored, so frames seen by a waiter are visible to read()

    def _take(self, msg: can.Message) -> None:
        ident = msg.arbitration_id
        if msg.is_error_frame:
            if ident & CAN_ERR_BUSOFF:
                self.bus_off = True
            return
        if not msg.is_extended_id or ident & ID_PREFIX_MASK != ID_PREFIX:
            return  # foreign traffic
        frame_type = ident & 0xFF
        data = msg.data
        problem = framing_problem(min(msg.dlc, len(data)), remote=msg.is_remote_frame, fd=msg.is_fd)
        if problem is not None:
            self._invalid(msg, problem)
            return
        if frame_type in _HOST_TYPES:
            return  # a host frame: our own echo or another tool on the bus
        if frame_type != _FEEDBACK1 and frame_type != _FEEDBACK2:
            if frame_type in _UNDECODED:
                self.undecoded_frames += 1
            else:
                self._invalid(msg, "unknown frame type")
            return
        slot = self._slot[(ident >> 8) & 0xFF]
        if slot < 0:
            return  # a Sito that is not ours
        now = self._clock()
        if frame_type == _FEEDBACK1:
            _, _, current, velocity = FEEDBACK1.unpack_from(data)
            with self.lock:
                self.raw[1, slot] = velocity
                self.raw[2, slot] = current
                self.stamp[0, slot] = now
        else:
            _, output = FEEDBACK2.unpack_from(data)
            with self.lock:
                self.raw[0, slot] = output
                self.stamp[1, slot] = now


    def _invalid(self, msg: can.Message, why: str) -> None:
        self.invalid_frames += 1
        self.last_invalid_stamp = self._clock()
        self.last_invalid = f"id 0x{msg.arbitration_id:08X} dlc {msg.dlc}: {why}"

    def on_error(self, exc: Exception) -> None:
        if is_interface_down(exc):
            self.down_error = str(exc) or type(exc).__name__
            time.sleep(_NOTIFIER_POLL_S)  # a dead interface fails every recv at once; do not spin
        else:
            self.invalid_frames += 1
            self.last_invalid_stamp = self._clock()
            self.last_invalid = f"undecodable frame: {exc}"


class SitoSystem(HardwareComponent):
    """The Sito wrists (``robot.hardware.sito_joints``) on one CAN bus."""

    def __init__(self, robot: Robot, calibration: Calibration, *, update_rate: float,
                 bus: can.BusABC | None = None, interface: str | None = None, channel: str | None = None,
                 rx_timeout_ms: float = 200.0, gain_refresh_s: float = 1.0, model: str = "TA40-50",
                 clock: Callable[[], float] = time.monotonic, emulated: bool = False) -> None:
        joints = robot.hardware.sito_joints
        self.emulated = emulated  # emulated wrists: a silence is the emulator's, there is no cable
        super().__init__(SITO_BLOCK, robot, joints)
        self.robot = robot
        self.can_ids = tuple(robot.hardware.mit_joints[j] for j in joints)
        try:
            self.model = sito_model(model)
            self.io_every, self.feedback_ms = bus_cycle(update_rate, len(joints), robot.hardware.can.bitrate)
        except ValueError as exc:
            raise PrimeError(f"{SITO_BLOCK}: {exc}") from None
        if not rx_timeout_ms > self.feedback_ms:
            raise PrimeError(f"{SITO_BLOCK}: rx_timeout_ms {rx_timeout_ms} must exceed the "
                             f"{self.feedback_ms} ms feedback interval at {update_rate} Hz")
        if not gain_refresh_s > 0:
            raise PrimeError(f"{SITO_BLOCK}: gain_refresh_s must be positive, got {gain_refresh_s}")
        self._scales = wire_scales(self.model)
        check_wire_limits(robot, self.model)
        self.channel = channel or robot.hardware.can.channel
        self.rx_timeout_s = rx_timeout_ms / 1000.0
        self.gain_refresh_s = gain_refresh_s
        self._interface, self._bus, self._owns_bus, self._clock = interface, bus, bus is None, clock
        self._notifier: can.Notifier | None = None
        self._rx = _FeedbackReceiver(self.can_ids, clock)
        self.frames_sent = self.send_failures = 0
        self._ticks_to_send = 0  # ticks until the next bus cycle's commands (0: this one)
        self._listening_since: float | None = None  # clock() of the first read since activation
        self._tx_down_error, self._tx_failed = "", False

        # The compiled read and write (``_tick.pyx``), packing by protocol's layout with protocol's scales, signed
        # by each joint's direction (gains carry none), the homing offset as a position bias in counts.
        sign = np.ones((5, len(joints)))
        sign[:3] = calibration.direction_array(joints)
        self._tick = SitoTick(self.indices, self._scales[:, None] * sign,
                              calibration.offset_array(joints) * self._scales[0], self._rx.raw, self._rx.stamp,
                              HOST_PAYLOADS, MIT_FIELDS)
        self._command_bytes = _payload_bytes(self._tick.payloads, "command")
        self._gains_bytes = _payload_bytes(self._tick.payloads, "gains")
        self._command_msgs = self._messages(FrameType.COMMAND, bytes(DATA_LENGTH))
        self._gains_msgs = self._messages(FrameType.GAINS, bytes(DATA_LENGTH))
        enable = ENABLE.pack(MODE_MIT, self.feedback_ms, self.feedback_ms, 0)  # feedback 1 and 2 every bus cycle
        self._enable_msgs = self._messages(FrameType.ENABLE, enable)
        self._disable_msgs = self._messages(FrameType.DISABLE, DISABLE_PAYLOAD)
        self._bus_flags = _bus_flags(self.channel, robot.hardware.can.bitrate)

    def _messages(self, frame_type: FrameType, data: bytes) -> list[can.Message]:
        """One frame of ``frame_type`` to each motor, carrying ``data`` until it is overwritten."""
        return [can.Message(arbitration_id=arbitration_id(can_id, frame_type), is_extended_id=True,
                            data=bytearray(data)) for can_id in self.can_ids]

    @property
    def bus(self) -> can.BusABC | None:
        return self._bus

    @property
    def frames_received(self) -> int:
        return self._rx.frames

    @property
    def invalid_frames(self) -> int:
        return self._rx.invalid_frames

    @property
    def undecoded_frames(self) -> int:
        """0xB0/0xB3 feedback frames received (valid, not decoded, ignored)."""
        return self._rx.undecoded_frames

    @property
    def last_invalid_frame(self) -> str:
        return self._rx.last_invalid

    # --- lifecycle -------------------------------------------------------------------------------------

    @property
    def _open_bus(self) -> can.BusABC:
        bus = self._bus
        assert bus is not None, "the bus opens in on_configure"
        return bus

    def on_configure(self) -> None:
        if self._bus is None:
            self._bus = open_bus(self.robot.hardware, interface=self._interface, channel=self.channel)

    def on_activate(self) -> None:
        for problem in ("bus_off", "interface_down"):
            self.clear_flag(self._bus_flags[problem][0])
        self._tx_down_error = ""
        self._listening_since = None
        self._ticks_to_send = 0
        self._rx.reset()
        self._notifier = can.Notifier(self._open_bus, [self._rx], timeout=_NOTIFIER_POLL_S)
        _EXIT_GUARD.add(self)
        try:
            now = self._clock()
            self._tick.payloads["gains"] = 0  # activation gains are zero: the wrists start limp
            for i in range(len(self.can_ids)):
                self._gains_msgs[i].data[:] = self._gains_bytes[i]
                self._send_or_raise(self._gains_msgs[i], i, "gains")
                self._tick.gains_sent_at(i, now)
            for i in range(len(self.can_ids)):
                self._send_or_raise(self._enable_msgs[i], i, "enable")
            self._wait_for_feedback()
        except BaseException:
            self._stop()
            raise

    def on_deactivate(self) -> None:
        self._stop()

    def on_shutdown(self) -> None:
        if self._owns_bus and self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def _stop(self) -> None:
        try:
            self.disable_motors()
        finally:
            _EXIT_GUARD.remove(self)
            if self._notifier is not None:
                self._notifier.stop(timeout=2 * _NOTIFIER_POLL_S + 1.0)
                self._notifier = None

    def disable_motors(self) -> None:
        """Send disable (reset) to every motor; never raises. Safe from any thread, any number of times."""
        bus = self._bus
        if bus is None:
            return
        for msg in self._disable_msgs:
            try:
                bus.send(msg, timeout=_LIFECYCLE_SEND_TIMEOUT_S)
                self.frames_sent += 1
            except (can.CanError, OSError, ValueError):
                self.send_failures += 1

    def _send_or_raise(self, msg: can.Message, slot: int, what: str) -> None:
        try:
            self._open_bus.send(msg, timeout=_LIFECYCLE_SEND_TIMEOUT_S)
        except (can.CanError, OSError) as exc:
            raise PrimeError(f"{self.joints[slot]} (CAN id {self.can_ids[slot]}): cannot send {what} on "
                             f"{self.channel}: {exc}; check that the interface is up and the wrists are powered"
                             ) from None
        self.frames_sent += 1

    def _wait_for_feedback(self) -> None:
        deadline = self._clock() + self.rx_timeout_s
        while True:
            with self._rx.lock:
                heard = np.isfinite(self._rx.stamp).all(axis=0)
            if heard.all():
                return
            if self._clock() >= deadline:
                break
            time.sleep(0.001)
        silent = ", ".join(f"{self.joints[i]} (CAN id {self.can_ids[i]})" for i in np.flatnonzero(~heard))
        raise PrimeError(f"no feedback on {self.channel} from {silent} within {self.rx_timeout_s * 1000:g} ms of "
                         "enable; check that the wrists are powered and the bus is wired and terminated")

    # --- per tick --------------------------------------------------------------------------------------

    def read(self, now: float, state: StateArrays) -> None:
        rx, tick = self._rx, self._tick
        clock_now = self._clock()
        limit = clock_now - self.rx_timeout_s
        since = self._listening_since
        if since is None:
            since = self._listening_since = clock_now
        with rx.lock:  # no wrist is late before the RX timeout has run from the first read (module docstring)
            rx_changed = tick.read(state.data, limit if limit > since else -math.inf)
        if rx_changed:
            for i in np.flatnonzero(tick.late != tick.rx_raised):
                self._motor_flag(bool(tick.late[i]), "rx_timeout", i, Level.ERROR)
            np.copyto(tick.rx_raised, tick.late)
        self._flag(rx.last_invalid_stamp >= limit, "invalid_frame", Level.WARN)
        if rx.bus_off:
            self._flag(True, "bus_off", Level.ERROR)
        down = rx.down_error or self._tx_down_error
        if down:
            key, text = self._bus_flags["interface_down"]
            if key not in self.flags:
                self.set_flag(key, text.format(down=down))

    def write(self, now: float, command: CommandArrays) -> None:
        if self._ticks_to_send:  # between bus cycles (control faster than the bus carries, module docstring)
            self._ticks_to_send -= 1
            self.io_s = 0.0
            return
        self._ticks_to_send = self.io_every - 1
        clock_now = self._clock()
        tick = self._tick
        # the payloads, which gains are due, and the command's problems (see SitoTick.write)
        problems_changed = tick.write(command.data, clock_now - self.gain_refresh_s)
        bus = self._open_bus
        failed = False
        began = time.perf_counter()  # the sends are this component's bus I/O (``io_s``)
        for i in range(len(self.can_ids)):
            if tick.gains_due[i]:
                msg = self._gains_msgs[i]
                msg.data[:] = self._gains_bytes[i]
                if self._send(bus, msg):
                    tick.gains_sent_at(i, clock_now)
                else:
                    failed = True
            msg = self._command_msgs[i]
            msg.data[:] = self._command_bytes[i]
            if not self._send(bus, msg):
                failed = True
        self.io_s = time.perf_counter() - began

        if failed != self._tx_failed:
            self._tx_failed = failed
            self._flag(failed and not self._tx_down_error, "tx_overrun", Level.WARN)
        if problems_changed:
            for row, i in zip(*np.nonzero(tick.problems != tick.problems_raised), strict=True):
                problem = "invalid_command" if row == INVALID else f"{COMMAND_NAMES[row]}_clamped"
                self._motor_flag(bool(tick.problems[row, i]), problem, i, Level.WARN)
            np.copyto(tick.problems_raised, tick.problems)

    def _send(self, bus: can.BusABC, msg: can.Message) -> bool:
        try:
            bus.send(msg, timeout=0.0)
        except (can.CanError, OSError) as exc:
            self.send_failures += 1
            if is_interface_down(exc) and not self._tx_down_error:
                self._tx_down_error = str(exc) or type(exc).__name__
            return False
        self.frames_sent += 1
        return True

    def _flag(self, raised: bool, problem: str, level: Level) -> None:
        """Raise or clear the transport flag ``<channel>/<problem>``."""
        key, text = self._bus_flags[problem]
        if raised:
            self.set_flag(key, text, level)
        else:
            self.clear_flag(key)

    def _motor_flag(self, raised: bool, problem: str, slot: int | np.intp, level: Level) -> None:
        """Raise or clear ``<channel>/<problem>/<CAN id>``; its words are only needed, and built, when raised."""
        can_id = self.can_ids[slot]
        key = f"{self.channel}/{problem}/{can_id}"
        if not raised:
            self.clear_flag(key)
            return
        who = f"{self.joints[slot]} (CAN id {can_id})"
        if problem == "rx_timeout":
            cause = ("the emulated wrist fell behind (a loaded machine) or the virtual Prime stopped" if self.emulated
                     else "check the motor's power and its CAN cable")
            text = f"{who} on {self.channel}: no feedback for more than {self.rx_timeout_s * 1000:g} ms; {cause}"
        elif problem == "invalid_command":
            text = f"{who}: non-finite, negative-gain or unrepresentable command; sent limp (zero gains and effort)"
        else:
            row = COMMAND_NAMES.index(problem.removesuffix("_clamped"))
            payload, field = MIT_FIELDS[row]
            reach = field_range(payload, field)[1] / self._scales[row]
            text = (f"{who}: commanded {COMMAND_NAMES[row]} beyond the {HOST_PAYLOADS[payload][field].name} wire "
                    f"range (±{reach:.3g} {_UNITS[row]}); sent clamped")
        self.set_flag(key, text, level)


def _payload_bytes(payloads: npt.NDArray[np.void], name: str) -> list[memoryview]:
    """Each motor's ``name`` payload as bytes: views of what the compiled write fills in place."""
    return [payloads[name][k:k + 1].view(np.uint8).data for k in range(len(payloads))]


def _bus_flags(channel: str, bitrate: int) -> dict[str, tuple[str, str]]:
    """The key and text of each transport flag of ``channel`` (``interface_down``'s text is a format)."""
    texts = {
        "bus_off": f"{channel}: CAN controller is bus-off (too many transmit errors); check wiring and termination, "
                   "then re-activate the wrists",
        "interface_down": f"{channel}: CAN interface is down or gone ({{down}}); bring it up (ip link set {channel} "
                          f"up type can bitrate {bitrate}) and re-activate the wrists",
        "tx_overrun": f"{channel}: transmit queue full (ENOBUFS): no node acknowledges our frames; usually the Sito "
                      "motors' power is off",
        "invalid_frame": f"{channel}: frames that break the Sito protocol (wrong length or unknown type) were "
                         "dropped; look for a foreign device or a wiring fault",
    }
    return {problem: (f"{channel}/{problem}", text) for problem, text in texts.items()}


def check_wire_limits(robot: Robot, model: str | SitoModel = "TA40-50", calibration: Calibration | None = None) -> None:
    """The hardware file's Sito command limits must fit the wire: a velocity its int16 field carries, gains the
    firmware's float32 fields carry; and each wrist's homing offset a position the wire carries."""
    scales = wire_scales(sito_model(model) if isinstance(model, str) else model)
    reach = field_range(*MIT_FIELDS[0])[1] / scales[0]
    if calibration is not None:
        for joint in robot.hardware.sito_joints:
            offset = calibration.joints[joint].homing_offset
            if abs(offset) > reach:
                raise ConfigError(calibration.path or "calibration", f"joints.{joint}.homing_offset",
                                  f"{offset:g} rad is beyond the positions the Sito wire carries (±{reach:.6g} rad)",
                                  "calibrate the joint again")
    limits = robot.hardware.command_limits["sito"]
    for row, name in ((1, "velocity"), (3, "stiffness"), (4, "damping")):
        reach = field_range(*MIT_FIELDS[row])[1] / scales[row]
        if getattr(limits, name) > reach:
            raise ConfigError(robot.hardware.path, f"command_limits.sito.{name}",
                              f"{getattr(limits, name):g} {_UNITS[row]} is beyond what the Sito wire carries "
                              f"({reach:.6g} {_UNITS[row]})", f"use at most {math.floor(reach * 100) / 100:g}")


# what signal.getsignal returns
_Handler = Callable[[int, types.FrameType | None], object] | int | None


class _ExitGuard:
    """Disables every active SitoSystem's motors at interpreter exit and on SIGINT/SIGTERM.

    A signal handler sends from a helper thread so it can never deadlock on a lock the interrupted
    main thread holds; then the previous handler runs as it would have.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self._systems: set[SitoSystem] = set()  # strong: an active system must outlive its last user
        self._previous: dict[int, _Handler] = {}
        self._lock = threading.Lock()
        atexit.register(self.disable_all)

    def add(self, system: SitoSystem) -> None:
        with self._lock:
            self._systems.add(system)
            if threading.current_thread() is threading.main_thread() and not self._previous:
                for signum in self.SIGNALS:
                    self._previous[signum] = signal.getsignal(signum)
                    signal.signal(signum, self._on_signal)

    def remove(self, system: SitoSystem) -> None:
        with self._lock:
            self._systems.discard(system)
            if not self._systems and self._previous and threading.current_thread() is threading.main_thread():
                for signum, previous in self._previous.items():
                    if signal.getsignal(signum) == self._on_signal:
                        signal.signal(signum, previous if previous is not None else signal.SIG_DFL)
                self._previous.clear()

    def disable_all(self) -> None:
        for system in list(self._systems):
            system.disable_motors()

    def _on_signal(self, signum: int, frame: types.FrameType | None) -> None:
        worker = threading.Thread(target=self.disable_all, name="sito-disable", daemon=True)
        worker.start()
        worker.join(1.0)
        previous = self._previous.get(signum, signal.SIG_DFL)
        if callable(previous):
            previous(signum, frame)
        elif previous != signal.SIG_IGN:
            signal.signal(signum, signal.SIG_DFL)
            with contextlib.suppress(OSError):
                os.kill(os.getpid(), signum)


_EXIT_GUARD = _ExitGuard()
