"""The safety flags of ``EthercatSystem`` (system.py), worded from what its master and its drives say: the
working counter, each slave lost or back, each drive's fault and each drive held disabled. A base class of its own
so that system.py keeps to the tick and the lifecycle; it reads the state system.py keeps and owns none."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.drivers.erob.cia402 import ERROR_HINTS, describe_error, drive_state
from humanoid_prime.drivers.erob.drive_state import Drive, Event, apply_event
from humanoid_prime.drivers.ethercat.master import EthercatMaster
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, describe_al_state, describe_al_status_code
from humanoid_prime.errors import PrimeError


class EthercatFlags(HardwareComponent):
    """Wording of the flags; the state it reads is kept by ``EthercatSystem``."""

    master: EthercatMaster | None
    emulated: bool
    ring: npt.NDArray[np.intp]
    wkc_tolerance_cycles: int
    on_restore_needed: Callable[[], None] | None
    _wkc_bad_cycles: int
    _wkc_flagged: bool
    _wkc_silent: bool
    _health_seen: int
    _left_op_seen: npt.NDArray[np.int64]
    _came_back: list[str]
    _state: npt.NDArray[np.uint8]
    _held_seen: npt.NDArray[np.bool_]
    _fault: npt.NDArray[np.bool_]
    _fault_seen: tuple[tuple[np.intp, int, int], ...]
    _rec_sw: npt.NDArray[np.uint16]
    _rec_err: npt.NDArray[np.uint16]

    def _master(self) -> EthercatMaster:
        if self.master is None:
            raise PrimeError(f"{self.name}: not configured")
        return self.master

    def _update_wkc_flag(self, wkc: int) -> None:
        master = self._master()
        self._wkc_flagged = self._wkc_bad_cycles >= self.wkc_tolerance_cycles
        self._wkc_silent = wkc <= 0
        if not self._wkc_flagged:
            self.clear_flag("ethercat/wkc")
        elif self._wkc_silent:
            # the supervision cannot name a slave then (every state read goes unanswered too)
            first = next((f"ring 0 ({joint})" for joint, position in zip(self.joints, self.ring, strict=True)
                          if position == 0), "ring 0")
            cause = ("the virtual Prime stopped answering or fell behind (a loaded machine)" if self.emulated else
                     f"the line is cut before the first drive; check the cable from {master.interface} and the "
                     f"power of {first}")
            self.set_flag("ethercat/wkc", f"no EtherCAT drive answered on {master.interface} for "
                                          f"{self._wkc_bad_cycles} cycles (working counter {wkc}): {cause}")
        else:
            self.set_flag("ethercat/wkc", f"EtherCAT working counter {wkc}, expected {master.expected_wkc} on "
                                          f"{master.interface} for {self._wkc_bad_cycles} cycles: process data is "
                                          "not reaching every drive")

    def _update_health_flags(self) -> None:
        master = self._master()
        self._health_seen = master.health_version
        lost = getattr(master, "lost", None)
        left = master.left_op[self.ring]
        again = left != self._left_op_seen
        for k, joint in enumerate(self.joints):
            position = int(self.ring[k])
            key = f"ethercat/ring{position}/lost"
            if master.slave_ok[position]:
                if again[k] and key not in self.flags:
                    # out of OP and back between two looks of the loop (a loop kept off the CPU while the keeper and
                    # the supervision went on): said for one tick, with why it left, never passed over
                    code = int(master.left_op_code[position])
                    why = f" (AL status 0x{code:04X} {describe_al_status_code(code)})" if code else ""
                    self.set_flag(key, f"{joint} (ring {position}): slave left OP{why} and came back")
                    self._came_back.append(key)
                else:
                    self.clear_flag(key)
                continue
            state, code = int(master.al_state[position]), int(master.al_status_code[position])
            why = "not answering" if lost is not None and lost[position] else f"in {describe_al_state(state)}"
            left_code = int(master.left_op_code[position])  # why it left, as its ESC said then
            if code and state & AL_ERROR and not (lost is not None and lost[position]):  # why it is not back, now
                why += f", AL status 0x{code:04X} {describe_al_status_code(code)}"
            elif left_code:  # its error acknowledged since (the recovery does), the reason it left is kept
                why += f"; it left OP with AL status 0x{left_code:04X} {describe_al_status_code(left_code)}"
            problem = master.recovery_problems.get(position)
            if problem:
                why += f"; {problem}"
            self.set_flag(key, f"{joint} (ring {position}): slave lost ({why}); recovering")
        # A held drive whose slave left OP again may have lost its settings again, restored or not: restore anew
        np.copyto(self._left_op_seen, left)
        if self.on_restore_needed is not None and again.any() and \
                apply_event(self._state, Event.LEFT_OP, where=again).any():
            self._update_held_flags()
        if self.on_restore_needed is not None and (self._state == Drive.RESTORING).any():  # its slave may be back
            self.on_restore_needed()

    def _update_fault_flags(self) -> None:
        faulted = tuple((k, int(self._rec_sw[k]), int(self._rec_err[k])) for k in np.flatnonzero(self._fault))
        if faulted == self._fault_seen:
            return
        now_faulted = {k for k, _, _ in faulted}
        for k, _, _ in self._fault_seen:
            if k not in now_faulted:
                self.clear_flag(f"ethercat/ring{int(self.ring[k])}/fault")
        for k, _, _ in faulted:
            self.set_flag(f"ethercat/ring{int(self.ring[k])}/fault",
                          f"{self._describe_drive(k)} (latched: r in the live table, or `prime reset`)")
        self._fault_seen = faulted

    def _update_held_flags(self) -> None:
        """The flags of the held drives, worded again (the loop's thread only). A drive newly held waits for its
        settings (RESTORING) when somebody restores them, and that somebody is woken."""
        held = self._state >= Drive.HELD
        wake = self.on_restore_needed
        if wake is not None:
            apply_event(self._state, Event.RESTORE_NEEDED, where=held & ~self._held_seen)
        for k in np.flatnonzero(held):
            self.set_flag(f"ethercat/ring{int(self.ring[k])}/disabled", self._held_text(k))
        for k in np.flatnonzero(self._held_seen & ~held):
            self.clear_flag(f"ethercat/ring{int(self.ring[k])}/disabled")
        np.copyto(self._held_seen, held)
        if wake is not None and (self._state == Drive.RESTORING).any():
            wake()

    def _held_text(self, k: int | np.intp) -> str:
        text = (f"{self.joints[k]} (ring {int(self.ring[k])}): the drive dropped out (power or link: it left "
                "operation, or its fault, by itself) and is held disabled, so it cannot snap to the target when it "
                "comes back")
        if self._state[k] == Drive.RESTORING:
            return f"{text}; its impedance settings are restored once it is back in OP, then r in the live table, " \
                   "or `prime reset`, enables it"
        return f"{text} (latched: r in the live table, or `prime reset`, once it is in OP)"

    def _describe_drive(self, k: int | np.intp) -> str:
        sw, err = int(self._rec_sw[k]), int(self._rec_err[k])
        text = (f"{self.joints[k]} (ring {int(self.ring[k])}): {drive_state(sw).value}, statusword {sw} "
                f"(0x{sw:04X}), error 0x{err:04X} {describe_error(err)}")
        hint = ERROR_HINTS.get(err)
        return f"{text}: {hint}" if hint else text
