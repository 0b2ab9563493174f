"""One eRob's impedance settings over SDO (DESIGN §2): its following-error window, the bus-gain gate and the three
loop-gain registers.

Every object is written with the size the drive reports for it (``SizedSdo``), with bounded retries, and logged.
The drive's own window is kept to be put back on ``reset``. Gains go out only those that change, in the order
that never leaves an intermediate pair stiffer than both modes (``write_order``). The impedance manager holds one
``DriveSettings`` per slave and works them from its workers; a drive's ``lock`` keeps one worker on it at a time.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import replace

from humanoid_prime.control.flags import Level
from humanoid_prime.drivers.erob.gains import ErobRegisters, write_order
from humanoid_prime.drivers.erob.objects import (
    BUS_GAIN_GATE,
    FOLLOWING_ERROR_WINDOW,
    POS_LOOP_GAIN,
    VEL_LOOP_GAIN,
    VEL_LOOP_INTEGRAL,
)
from humanoid_prime.drivers.ethercat.sdo_client import SizedSdo
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.gain_switch import SlaveSwitch

RETRY_BACKOFF_S = 0.005
WINDOW = (FOLLOWING_ERROR_WINDOW, 0x00)
_NAMES = {POS_LOOP_GAIN: "pos_reg", VEL_LOOP_GAIN: "vel_reg", VEL_LOOP_INTEGRAL: "integral"}
_LOGGED = {**_NAMES, BUS_GAIN_GATE: "gate", WINDOW: "following_window"}

Problem = tuple[str, Level]  # what a flag on the drive's slave says, and how bad it is
Written = tuple[tuple[str, int], ...]  # (register, value) in the order written


class DriveSettings:
    """The settings of the drive at ring ``position``. ``window_counts`` is the following-error window the run needs
    (None: leave the drive's); ``closing`` set means the run is ending and nothing more is armed; every write that
    goes through is appended to ``log`` as (clock, position, register, value)."""

    def __init__(self, joint: str, position: int, objects: SizedSdo, window_counts: int | None, *, retries: int,
                 closing: threading.Event, log: list[tuple[float, int, str, int]],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.joint = joint
        self.position = position
        self.window_counts = window_counts
        self.registers: ErobRegisters | None = None  # what the drive holds now; None = unknown
        self.gate_armed = False
        self.factory_window: int | None = None  # the drive's own window, put back by ``reset``
        self.written = 0  # gain writes so far: a read-back that finds this moved on is for an older switch
        self.lock = threading.Lock()
        self._objects = objects
        self._retries = retries
        self._closing = closing
        self._log = log
        self._clock = clock

    @property
    def where(self) -> str:
        return f"{self.joint} (ring {self.position})"

    def arm(self, again: bool = False) -> Problem | None:
        """The window, then the gate, then learn what the gain registers hold; ``again`` for a drive that may have
        lost both (back from a drop). Nothing once the run is closing."""
        with self.lock:
            if self._closing.is_set():  # the run resets this drive after us, or has already: arm nothing
                return None
            try:
                if self.window_counts is not None and (self.factory_window is None or again):
                    if self.factory_window is None:
                        self.factory_window = self._objects.read(self.position, WINDOW)
                    self._write(WINDOW, max(self.window_counts, self.factory_window))
                self._write(BUS_GAIN_GATE, 1)
            except Exception as exc:
                self.registers = None
                return f"{self.where}: gate not armed, no gains will be written until it is: {exc}", Level.ERROR
            self.gate_armed = True
            try:
                self.registers = self._read_registers()
            except Exception as exc:  # armed; the registers are unknown, so the next switch writes all three
                self.registers = None
                return (f"{self.where}: gate armed, gain registers not read back ({exc}); all three will be "
                        "written", Level.WARN)
        return None

    def write_gains(self, mode: Mode, new: ErobRegisters, before_last: Callable[[], None] | None = None
                    ) -> tuple[Written, int, str | None]:
        """``mode``'s registers to the armed drive, only those that change, in the safe order: (what was
        written, retries, error or None). ``before_last`` runs before the last write."""
        written: list[tuple[str, int]] = []
        retries = 0
        with self.lock:
            try:
                writes = write_order(self.registers, new)
                for k, (address, value) in enumerate(writes):
                    if k == len(writes) - 1 and before_last is not None:
                        before_last()
                    self.written += 1
                    retries += self._write(address, value)
                    written.append((_NAMES[address], value))
                    self.registers = _updated(self.registers, address, value)
                self.registers = new
                error = None
            except Exception as exc:
                done = ", ".join(name for name, _ in written) or "nothing"
                error = f"{mode.value} gains not fully applied ({done} written): {exc}"
        return tuple(written), retries, error

    def check(self, switch: SlaveSwitch, written: int, want: ErobRegisters) -> None:
        """Read the gains back after ``switch``, which left ``written`` gain writes made, into ``switch``: what the
        drive holds, and how it differs from ``want``. A drive holding other values counts as unknown (the next
        switch writes all three). Nothing if a later switch has written it meanwhile: its own read-back checks."""
        with self.lock:
            if self.written != written:
                return
            try:
                held = self._read_registers()
            except Exception as exc:
                switch.read_back_error = f"gains not read back: {exc}"
                return
            switch.read_back = {"pos_reg": held.pos_reg, "vel_reg": held.vel_reg, "integral": held.integral}
            if held != want:
                self.registers = None
                switch.read_back_error = (
                    f"{switch.mode} switch: gains read back as {switch.read_back}, not "
                    f"{dict(pos_reg=want.pos_reg, vel_reg=want.vel_reg, integral=want.integral)}")

    def restore(self, current: tuple[Mode, ErobRegisters] | None) -> Problem | None:
        """Back from a drop: window and gate again, then the ``current`` mode's gains (all three: a drive that lost
        power holds its factory gains, so what it holds is read anew)."""
        with self.lock:
            self.gate_armed = False
            self.registers = None
        problem = self.arm(again=True)
        if problem is not None and problem[1] is Level.ERROR:
            return f"{problem[0]}; its drive stays held disabled", Level.ERROR
        if not self.gate_armed:  # closing
            return None
        if current is None:
            return problem
        _written, _retries, error = self.write_gains(*current)
        if error is not None:
            return f"{self.where}: back from a drop, {error}; its drive stays held disabled", Level.ERROR
        return None  # the registers are known again, whether or not they could be read back

    def reset(self) -> str | None:
        """The gate back to 0 (the next bringup starts on factory gains), then the drive's own window; what failed,
        or None."""
        problems = []
        with self.lock:
            try:
                self._write(BUS_GAIN_GATE, 0)
            except Exception as exc:
                problems.append(f"gate not reset: {exc}")
            if self.factory_window is not None:
                try:
                    self._write(WINDOW, self.factory_window)
                    self.factory_window = None
                except Exception as exc:
                    problems.append(f"following-error window not restored to {self.factory_window}: {exc}")
        return f"{self.where}: " + "; ".join(problems) if problems else None

    def _write(self, address: tuple[int, int], value: int) -> int:
        """Write one object with bounded retries; returns the retries used, raises the last error."""
        for attempt in range(self._retries + 1):
            try:
                self._objects.write(self.position, address, value)
                self._log.append((self._clock(), self.position, _LOGGED[address], value))
                return attempt
            except Exception:
                if attempt == self._retries:
                    raise
                time.sleep(RETRY_BACKOFF_S * (attempt + 1))  # a recovering slave needs a moment, not a burst
        return self._retries

    def _read_registers(self) -> ErobRegisters:
        read = self._objects.read
        return ErobRegisters(pos_reg=read(self.position, POS_LOOP_GAIN), vel_reg=read(self.position, VEL_LOOP_GAIN),
                             integral=read(self.position, VEL_LOOP_INTEGRAL))


def _updated(regs: ErobRegisters | None, address: tuple[int, int], value: int) -> ErobRegisters | None:
    if regs is None:
        return None
    return replace(regs, **{_NAMES[address]: value})
