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
from collections.abc import Callable

import can
import numpy as np

from humanoid_prime.config.calibration import Calibration
from humanoid_prime.config.description import SITO_BLOCK
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import Level
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.drivers.sito._tick import SitoTick
from humanoid_prime.drivers.sito.bus import CAN_ERR_BUSOFF, bus_cycle, is_interface_down, open_bus
from humanoid_prime.drivers.sito.protocol import (
    COMMAND_DTYPE,
    COUNTS_PER_RAD,
    DATA_LENGTH,
    DISABLE_PAYLOAD,
    ENABLE,
    FEEDBACK1,
    FEEDBACK2,
    GAINS_DTYPE,
    HOST_FRAME_TYPES,
    ID_PREFIX,
    ID_PREFIX_MASK,
    INT16_MAX,
    MODE_MIT,
    UNDECODED_FEEDBACK_TYPES,
    FrameType,
    arbitration_id,
    sito_model,
)
from humanoid_prime.errors import PrimeError

_HOST_TYPES = frozenset(int(t) for t in HOST_FRAME_TYPES)
_FEEDBACK1 = int(FrameType.FEEDBACK1)
_FEEDBACK2 = int(FrameType.FEEDBACK2)
_UNDECODED = frozenset(int(t) for t in UNDECODED_FEEDBACK_TYPES)
_LIFECYCLE_SEND_TIMEOUT_S = 0.02  # gains, enable, disable may wait for queue space; per-tick frames never do
_NOTIFIER_POLL_S = 0.05  # how long stop() can wait for the receive thread


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
        if msg.is_remote_frame or msg.is_fd or msg.dlc != DATA_LENGTH or len(data) != DATA_LENGTH:
            self._invalid(msg, "wrong length or frame kind")
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
        self.last_invalid = (f"id 0x{msg.arbitration_id:08X} dlc {msg.dlc}"
                             f"{' remote' if msg.is_remote_frame else ''}: {why}")

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
                 clock: Callable[[], float] = time.monotonic) -> None:
        joints = robot.hardware.sito_joints
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
        self.channel = channel or robot.hardware.can.channel
        self.rx_timeout_s = rx_timeout_ms / 1000.0
        self.gain_refresh_s = gain_refresh_s
        self._interface = interface
        self._bus = bus
        self._owns_bus = bus is None
        self._clock = clock
        self._notifier: can.Notifier | None = None
        self._rx = _FeedbackReceiver(self.can_ids, clock)
        self.frames_sent = 0
        self.send_failures = 0

        n = len(joints)
        direction = calibration.direction_array(joints)
        self._direction = direction
        self._offset = calibration.offset_array(joints)
        # joint frame -> wire: rows position counts, velocity counts/s, ff current mA
        self._to_wire = np.stack([direction * COUNTS_PER_RAD, direction * COUNTS_PER_RAD,
                                  direction / self.model.nm_per_mA])
        self._wire_bias = np.stack([self._offset * COUNTS_PER_RAD, np.zeros(n), np.zeros(n)])
        # wire -> joint frame: rows position, velocity, effort (position also subtracts direction * offset)
        self._from_wire = np.stack([direction / COUNTS_PER_RAD, direction / COUNTS_PER_RAD,
                                    direction * self.model.nm_per_mA])
        self._state_bias = direction * self._offset

        # Hot-path buffers.
        self._late = np.zeros(n, dtype=bool)
        self._ticks_to_send = 0  # ticks until the next bus cycle's commands (0: this one)
        self._listening_since: float | None = None  # clock() of the first read since activation
        self._command_payload = np.zeros(n, dtype=COMMAND_DTYPE)
        self._gains_payload = np.zeros(n, dtype=GAINS_DTYPE)
        self._gains_word = self._gains_payload.view(np.uint64)  # one word per motor: compare gains bitwise
        self._gains_sent = np.zeros(n, dtype=np.uint64)
        self._gains_stamp = np.zeros(n)
        self._gains_due = np.zeros(n, dtype=bool)
        command_rows = self._command_payload.view(np.uint8).reshape(n, DATA_LENGTH)
        gains_rows = self._gains_payload.view(np.uint8).reshape(n, DATA_LENGTH)
        self._command_bytes = [memoryview(command_rows[i]) for i in range(n)]
        self._gains_bytes = [memoryview(gains_rows[i]) for i in range(n)]
        self._command_msgs = [self._message(i, FrameType.COMMAND, bytes(DATA_LENGTH)) for i in range(n)]
        self._gains_msgs = [self._message(i, FrameType.GAINS, bytes(DATA_LENGTH)) for i in range(n)]
        enable = ENABLE.pack(MODE_MIT, self.feedback_ms, self.feedback_ms, 0)
        self._enable_msgs = [self._message(i, FrameType.ENABLE, enable) for i in range(n)]
        self._disable_msgs = [self._message(i, FrameType.DISABLE, DISABLE_PAYLOAD) for i in range(n)]
        # Per-motor command problems, rows: velocity clamped, effort clamped, invalid command.
        self._problems = np.zeros((3, n), dtype=bool)
        self._problems_raised = np.zeros((3, n), dtype=bool)
        self._rx_raised = np.zeros(n, dtype=bool)
        # the compiled read and write (``_tick.pyx``), bound to the arrays above
        u8 = np.uint8
        self._tick = SitoTick(self.indices, self._to_wire, self._wire_bias, self._from_wire, self._state_bias,
                              self._rx.raw, self._rx.stamp, self._late.view(u8), self._rx_raised.view(u8),
                              self._problems.view(u8), self._problems_raised.view(u8), command_rows, gains_rows,
                              self._gains_word, self._gains_sent, self._gains_stamp, self._gains_due.view(u8),
                              self.model.kp_divisor, self.model.kd_divisor)

        # Flags: keys and texts built once; per tick only the raised/cleared state is compared.
        ch = self.channel
        who = [f"{j} (CAN id {i})" for j, i in zip(joints, self.can_ids, strict=True)]
        self._rx_keys = [f"{ch}/rx_timeout/{i}" for i in self.can_ids]
        self._rx_texts = [f"{w} on {ch}: no feedback for more than {rx_timeout_ms:g} ms; "
                          "check the motor's power and its CAN cable" for w in who]
        self._velocity_keys = [f"{ch}/velocity_clamped/{i}" for i in self.can_ids]
        self._velocity_texts = [f"{w}: commanded velocity beyond the int16 wire range "
                                f"(±{INT16_MAX / COUNTS_PER_RAD:.2f} rad/s); sent clamped" for w in who]
        self._effort_keys = [f"{ch}/effort_clamped/{i}" for i in self.can_ids]
        self._effort_texts = [f"{w}: commanded effort beyond the int16 current range "
                              f"(±{INT16_MAX * self.model.nm_per_mA:.1f} Nm); sent clamped" for w in who]
        self._command_keys = [f"{ch}/invalid_command/{i}" for i in self.can_ids]
        self._command_texts = [f"{w}: non-finite or negative-gain command; sent limp (zero gains and effort)"
                               for w in who]
        self._bus_off_key = f"{ch}/bus_off"
        self._bus_off_text = (f"{ch}: CAN controller is bus-off (too many transmit errors); check wiring and "
                              "termination, then re-activate the wrists")
        self._down_key = f"{ch}/interface_down"
        self._tx_key = f"{ch}/tx_overrun"
        self._tx_text = (f"{ch}: transmit queue full (ENOBUFS): no node acknowledges our frames; "
                         "usually the Sito motors' power is off")
        self._invalid_key = f"{ch}/invalid_frame"
        self._invalid_text = (f"{ch}: frames that break the Sito protocol (wrong length or unknown type) were "
                              "dropped; look for a foreign device or a wiring fault")
        self._problem_flags = ((self._velocity_keys, self._velocity_texts), (self._effort_keys, self._effort_texts),
                               (self._command_keys, self._command_texts))
        self._tx_down_error = ""
        self._tx_failed = False

    def _message(self, slot: int, frame_type: FrameType, data: bytes) -> can.Message:
        return can.Message(arbitration_id=arbitration_id(self.can_ids[slot], frame_type), is_extended_id=True,
                           data=bytearray(data))

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

    def on_configure(self) -> None:
        if self._bus is None:
            self._bus = open_bus(self.robot.hardware, interface=self._interface, channel=self.channel)

    def on_activate(self) -> None:
        for key in (self._bus_off_key, self._down_key):
            self.clear_flag(key)
        self._tx_down_error = ""
        self._listening_since = None
        self._ticks_to_send = 0
        self._rx.reset()
        self._notifier = can.Notifier(self._bus, [self._rx], timeout=_NOTIFIER_POLL_S)
        _EXIT_GUARD.add(self)
        try:
            now = self._clock()
            self._gains_payload[:] = 0  # activation gains are zero: the wrists start limp
            self._gains_sent[:] = self._gains_word
            self._gains_stamp[:] = now
            for i in range(len(self.can_ids)):
                self._gains_msgs[i].data[:] = self._gains_bytes[i]
                self._send_or_raise(self._gains_msgs[i], i, "gains")
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
            self._bus.send(msg, timeout=_LIFECYCLE_SEND_TIMEOUT_S)
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
        rx = self._rx
        clock_now = self._clock()
        limit = clock_now - self.rx_timeout_s
        since = self._listening_since
        if since is None:
            since = self._listening_since = clock_now
        with rx.lock:  # no wrist is late before the RX timeout has run from the first read (module docstring)
            rx_changed = self._tick.read(state.data, limit if limit > since else -math.inf)
        if rx_changed:
            for i in np.flatnonzero(self._late != self._rx_raised):
                self._flag(bool(self._late[i]), self._rx_keys[i], self._rx_texts[i], Level.ERROR)
            np.copyto(self._rx_raised, self._late)
        self._flag(rx.last_invalid_stamp >= limit, self._invalid_key, self._invalid_text, Level.WARN)
        if rx.bus_off:
            self.set_flag(self._bus_off_key, self._bus_off_text)
        down = rx.down_error or self._tx_down_error
        if down and self._down_key not in self.flags:
            self.set_flag(self._down_key, f"{self.channel}: CAN interface is down or gone ({down}); bring it up "
                                          f"(ip link set {self.channel} up type can bitrate "
                                          f"{self.robot.hardware.can.bitrate}) and re-activate the wrists")

    def write(self, now: float, command: CommandArrays) -> None:
        if self._ticks_to_send:  # between bus cycles (control faster than the bus carries, module docstring)
            self._ticks_to_send -= 1
            self.io_s = 0.0
            return
        self._ticks_to_send = self.io_every - 1
        clock_now = self._clock()
        # the payloads, which gains are due, and the command's problems (see SitoTick.write)
        problems_changed = self._tick.write(command.data, clock_now - self.gain_refresh_s)
        bus = self._bus
        failed = False
        began = time.perf_counter()  # the sends are this component's bus I/O (``io_s``)
        for i in range(len(self.can_ids)):
            if self._gains_due[i]:
                msg = self._gains_msgs[i]
                msg.data[:] = self._gains_bytes[i]
                if self._send(bus, msg):
                    self._gains_sent[i] = self._gains_word[i]
                    self._gains_stamp[i] = clock_now
                else:
                    failed = True
            msg = self._command_msgs[i]
            msg.data[:] = self._command_bytes[i]
            if not self._send(bus, msg):
                failed = True
        self.io_s = time.perf_counter() - began

        if failed != self._tx_failed:
            self._tx_failed = failed
            self._flag(failed and not self._tx_down_error, self._tx_key, self._tx_text, Level.WARN)
        if problems_changed:
            problems = self._problems
            for row, i in zip(*np.nonzero(problems != self._problems_raised), strict=True):
                keys, texts = self._problem_flags[row]
                self._flag(bool(problems[row, i]), keys[i], texts[i], Level.WARN)
            np.copyto(self._problems_raised, problems)

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

    def _flag(self, raised: bool, key: str, text: str, level: Level) -> None:
        if raised:
            self.set_flag(key, text, level)
        else:
            self.clear_flag(key)


class _ExitGuard:
    """Disables every active SitoSystem's motors at interpreter exit and on SIGINT/SIGTERM.

    A signal handler sends from a helper thread so it can never deadlock on a lock the interrupted
    main thread holds; then the previous handler runs as it would have.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self._systems: set[SitoSystem] = set()  # strong: an active system must outlive its last user
        self._previous: dict[int, object] = {}
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

    def _on_signal(self, signum: int, frame: object) -> None:
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
