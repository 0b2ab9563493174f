"""Damped limp of one eRob for a hand sweep, restoring the drive exactly as found on every exit path.

Procedure (DESIGN §5): snapshot the gate and the three gain registers, arm the gate (0x2383 = 1),
position gain 0, velocity integral 0, keep the velocity gain (damping, so gravity gives a slow
descent) or set a lower one, read back and show Kp = 0. On leaving — normal, Ctrl-C, SIGTERM, an
exception, a lost bus — write the snapshot back (gains first, in the never-stiffer order, then the
gate) and report any register that could not be restored.
"""

from __future__ import annotations

import signal
import threading
from dataclasses import dataclass

from humanoid_prime.drivers.erob.gains import ErobRegisters, write_order
from humanoid_prime.drivers.erob.objects import (
    BUS_GAIN_GATE,
    POS_LOOP_GAIN,
    VEL_LOOP_GAIN,
    VEL_LOOP_INTEGRAL,
)
from humanoid_prime.drivers.ethercat.sdo import SdoClient, SizedSdo
from humanoid_prime.errors import PrimeError

REGISTER_NAMES = {POS_LOOP_GAIN: "pos_reg 0x2382:01", VEL_LOOP_GAIN: "vel_reg 0x2381:01",
                  VEL_LOOP_INTEGRAL: "integral 0x2381:02", BUS_GAIN_GATE: "gate 0x2383"}


@dataclass(frozen=True)
class GainSnapshot:
    gate: int
    registers: ErobRegisters


def read_snapshot(objects: SizedSdo, position: int) -> GainSnapshot:
    """The gate and the three gain registers as the drive holds them (learning each object's size)."""
    return GainSnapshot(
        gate=objects.read(position, BUS_GAIN_GATE),
        registers=ErobRegisters(
            pos_reg=objects.read(position, POS_LOOP_GAIN),
            vel_reg=objects.read(position, VEL_LOOP_GAIN),
            integral=objects.read(position, VEL_LOOP_INTEGRAL),
        ),
    )


class DampedLimp:
    """Context manager: the eRob at ``position`` is damped-limp inside the ``with`` block.

    ``vel_reg`` sets the damping register during the limp; None keeps the drive's current value
    (with the gate at 0 that is what the registers hold, not the factory gains in use).
    """

    def __init__(self, sdo: SdoClient, position: int, vel_reg: int | None = None) -> None:
        if vel_reg is not None and vel_reg < 0:
            raise PrimeError(f"ring {position}: damping register must be >= 0, got {vel_reg}")
        self.objects = SizedSdo(sdo)
        self.position = position
        self.vel_reg = vel_reg
        self.snapshot: GainSnapshot | None = None
        self.readback: GainSnapshot | None = None
        self.unrestored: list[str] = []

    def _write(self, address: tuple[int, int], value: int) -> None:
        self.objects.write(self.position, address, value)

    def __enter__(self) -> DampedLimp:
        self.snapshot = read_snapshot(self.objects, self.position)
        try:
            limp = ErobRegisters(pos_reg=0, vel_reg=self.snapshot.registers.vel_reg if self.vel_reg is None
                                 else self.vel_reg, integral=0)
            self._write(BUS_GAIN_GATE, 1)
            for address, value in write_order(self.snapshot.registers, limp):
                self._write(address, value)
            self.readback = read_snapshot(self.objects, self.position)
            if self.readback.gate != 1 or self.readback.registers.pos_reg != 0:
                raise PrimeError(
                    f"ring {self.position}: limp did not take (read back gate={self.readback.gate}, "
                    f"pos_reg={self.readback.registers.pos_reg}); the drive is still stiff")
        except BaseException:
            self.restore()
            raise
        return self

    def restore(self) -> list[str]:
        """Write the snapshot back; returns (and keeps) the registers that could not be restored.

        Signals are held off while it runs, so an impatient Ctrl-C cannot leave the pair half-written."""
        assert self.snapshot is not None
        self.unrestored = []
        held = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
        on_main_thread = threading.current_thread() is threading.main_thread()
        if on_main_thread:
            signal.pthread_sigmask(signal.SIG_BLOCK, held)
        try:
            try:
                current = read_snapshot(self.objects, self.position).registers
            except Exception:
                current = self.readback.registers if self.readback is not None else None
            for address, value in write_order(current, self.snapshot.registers):
                try:
                    self._write(address, value)
                except Exception as exc:
                    self.unrestored.append(f"{REGISTER_NAMES[address]} (wanted {value}): {exc}")
            try:
                self._write(BUS_GAIN_GATE, self.snapshot.gate)
            except Exception as exc:
                self.unrestored.append(f"{REGISTER_NAMES[BUS_GAIN_GATE]} (wanted {self.snapshot.gate}): {exc}")
        finally:
            if on_main_thread:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, held)
        return self.unrestored

    def __exit__(self, *exc: object) -> None:
        self.restore()
        if self.unrestored:
            raise PrimeError(f"ring {self.position}: could not restore " + "; ".join(self.unrestored))
