"""Gain overrides of one eRob, restoring the drive exactly as found on every exit path.

``GainOverride`` is the shared procedure: snapshot the gate, the three gain registers and any further objects
it is asked to set, arm the gate (0x2383 = 1), write the wanted registers (only those that change, in the
never-stiffer order), and on leaving — normal, Ctrl-C, SIGTERM, an exception, a lost bus — write the snapshot
back (gains first, then the gate, then the further objects) and report anything that could not be restored.
Given a journal, it keeps a record of what it found before its first write, removed once the drive is restored,
so that a process killed where no exit path runs leaves the next command what to restore (``restore_left``).

``DampedLimp`` is the hand sweep's limp (DESIGN §5): position gain 0, integral 0, the velocity gain kept
(damping, so gravity gives a slow descent) or set lower, read back to show Kp = 0. ``prime calibrate --auto``
overrides the gains with its approach impedance and sets the following-error window and the drive's own
torque limit with them.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from humanoid_prime.calibration.journal import OverrideJournal, OverrideRecord
from humanoid_prime.drivers.erob.gains import ErobRegisters, write_order
from humanoid_prime.drivers.erob.objects import (
    BUS_GAIN_GATE,
    POS_LOOP_GAIN,
    VEL_LOOP_GAIN,
    VEL_LOOP_INTEGRAL,
)
from humanoid_prime.drivers.ethercat.sdo_client import SdoClient, SizedSdo
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


def _name(address: tuple[int, int]) -> str:
    return REGISTER_NAMES.get(address, f"0x{address[0]:04X}:{address[1]:02X}")


def write_back(objects: SizedSdo, position: int, snapshot: GainSnapshot, extra: Mapping[tuple[int, int], int],
               current: ErobRegisters | None) -> list[str]:
    """Write ``snapshot`` and ``extra`` back from ``current`` (None: not known): the gains in the never-stiffer
    order, then the gate, then the further objects; returns what could not be written, one entry each."""
    unrestored = []
    for address, value in [*write_order(current, snapshot.registers), (BUS_GAIN_GATE, snapshot.gate),
                           *extra.items()]:
        try:
            objects.write(position, address, value)
        except Exception as exc:
            unrestored.append(f"{_name(address)} (wanted {value}): {exc}")
    return unrestored


class GainOverride:
    """Context manager: inside the ``with`` block the eRob at ``position`` runs on the registers ``wanted`` (or
    those it returns for the drive's snapshot), with the gate armed and each of ``objects`` ((index, sub) -> value)
    set.

    ``optional`` objects are set only where the drive has them: one that cannot be read is left out and named
    in ``missing`` (object -> why), so the caller can say so. Each of ``objects`` is written before the gate
    and the gains (a wider following-error window must be in place before a softer joint sags)."""

    left_as = "with overridden gains"  # how the drive is while overridden, for a record left behind

    def __init__(self, sdo: SdoClient, position: int,
                 wanted: ErobRegisters | Callable[[GainSnapshot], ErobRegisters], *,
                 objects: Mapping[tuple[int, int], int] | None = None,
                 optional: Mapping[tuple[int, int], int] | None = None,
                 journal: tuple[OverrideJournal, str] | None = None) -> None:
        self.objects = SizedSdo(sdo)
        self.journal = journal  # (the journal, the joint's name): a record kept while the drive is overridden
        self.recorded = False
        self.position = position
        self.wanted = wanted
        self.extra = dict(objects or {})
        self.optional = dict(optional or {})
        self.snapshot: GainSnapshot | None = None
        self.extra_snapshot: dict[tuple[int, int], int] = {}
        self.missing: dict[tuple[int, int], str] = {}
        self.applied: ErobRegisters | None = None
        self.unrestored: list[str] = []

    def _write(self, address: tuple[int, int], value: int) -> None:
        self.objects.write(self.position, address, value)

    def __enter__(self) -> GainOverride:
        self.snapshot = read_snapshot(self.objects, self.position)
        try:
            for address in self.extra:
                self.extra_snapshot[address] = self.objects.read(self.position, address)
            for address in self.optional:
                try:
                    self.extra_snapshot[address] = self.objects.read(self.position, address)
                except PrimeError as exc:
                    self.missing[address] = str(exc)
            if self.journal is not None:  # before the first write: a kill from here on leaves what to restore
                journal, joint = self.journal
                registers = self.snapshot.registers
                journal.record(self.position, joint, {"gate": self.snapshot.gate, "pos_reg": registers.pos_reg,
                                                      "vel_reg": registers.vel_reg, "integral": registers.integral},
                               self.extra_snapshot, self.left_as)
                self.recorded = True
            for address, value in {**self.extra, **self.optional}.items():
                if address in self.extra_snapshot:
                    self._write(address, value)
            self._write(BUS_GAIN_GATE, 1)
            self.applied = self.wanted if isinstance(self.wanted, ErobRegisters) else self.wanted(self.snapshot)
            for address, value in write_order(self.snapshot.registers, self.applied):
                self._write(address, value)
            self.check()
        except BaseException:
            self.restore()
            raise
        return self

    def check(self) -> None:
        """Raise if the override did not take (a subclass reads back what matters to it)."""

    def restore(self) -> list[str]:
        """Write the snapshot back; returns (and keeps) what could not be restored.

        Signals are held off while it runs, so an impatient Ctrl-C cannot leave the pair half-written."""
        assert self.snapshot is not None
        self.unrestored = []
        held = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
        on_main_thread = threading.current_thread() is threading.main_thread()
        if on_main_thread:
            signal.pthread_sigmask(signal.SIG_BLOCK, held)
        try:
            try:
                current: ErobRegisters | None = read_snapshot(self.objects, self.position).registers
            except Exception:
                current = self.applied
            self.unrestored = write_back(self.objects, self.position, self.snapshot, self.extra_snapshot, current)
            if self.recorded and not self.unrestored:
                assert self.journal is not None
                self.journal[0].clear(self.position)
                self.recorded = False
        finally:
            if on_main_thread:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, held)
        return self.unrestored

    def __exit__(self, *exc: object) -> None:
        self.restore()
        if self.unrestored:
            raise PrimeError(f"ring {self.position}: could not restore " + "; ".join(self.unrestored))


def restore_left(sdo: SdoClient, journal: OverrideJournal) -> list[tuple[int, str]]:
    """Restore every drive an override recorded in ``journal`` and left so (its process ended without restoring
    it), from what the record says the drive held; (ring position, a line saying so) per drive. A drive that cannot
    be restored raises PrimeError, its record kept for the next try."""
    objects = SizedSdo(sdo)
    lines = []
    for record in journal.left():
        snapshot = _found(record)
        try:
            current: ErobRegisters | None = read_snapshot(objects, record.position).registers
        except Exception:
            current = None
        unrestored = write_back(objects, record.position, snapshot, record.objects, current)
        if unrestored:
            raise PrimeError(f"{record.describe()}; it could not be restored: {'; '.join(unrestored)} (the record "
                             f"stays in {record.path.parent} for the next try)")
        journal.clear(record.position)
        found = " ".join(f"{name}={value}" for name, value in record.found.items())
        lines.append((record.position, f"{record.describe()}: restored its gains as found, {found}"))
    return lines


def _found(record: OverrideRecord) -> GainSnapshot:
    return GainSnapshot(record.found["gate"], ErobRegisters(pos_reg=record.found["pos_reg"],
                                                            vel_reg=record.found["vel_reg"],
                                                            integral=record.found["integral"]))


class DampedLimp(GainOverride):
    """Context manager: the eRob at ``position`` is damped-limp inside the ``with`` block.

    ``vel_reg`` sets the damping register during the limp; None keeps the drive's current value
    (with the gate at 0 that is what the registers hold, not the factory gains in use).
    """

    left_as = "limp"

    def __init__(self, sdo: SdoClient, position: int, vel_reg: int | None = None, *,
                 journal: tuple[OverrideJournal, str] | None = None) -> None:
        if vel_reg is not None and vel_reg < 0:
            raise PrimeError(f"ring {position}: damping register must be >= 0, got {vel_reg}")
        self.vel_reg = vel_reg
        self.readback: GainSnapshot | None = None
        super().__init__(sdo, position, self._limp, journal=journal)

    def _limp(self, snapshot: GainSnapshot) -> ErobRegisters:
        vel_reg = snapshot.registers.vel_reg if self.vel_reg is None else self.vel_reg
        return ErobRegisters(pos_reg=0, vel_reg=vel_reg, integral=0)

    def check(self) -> None:
        self.readback = read_snapshot(self.objects, self.position)
        if self.readback.gate != 1 or self.readback.registers.pos_reg != 0:
            raise PrimeError(
                f"ring {self.position}: limp did not take (read back gate={self.readback.gate}, "
                f"pos_reg={self.readback.registers.pos_reg}); the drive is still stiff")
