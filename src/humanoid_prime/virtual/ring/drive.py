"""The eRob drive model behind one emulated slave: object dictionary, CiA402 state machine and the CSP
cascaded position -> velocity loop in SI units (DESIGN §2). Pure Python, steppable, no bus.

Loop (CSP, mode 8): ``v_cmd = Kpos * (target - q) + v_offset``; ``tau = Kvel * (v_cmd - qd) + I +
tau_offset`` with ``I`` integrating ``Ki * (v_cmd - qd)``; ``tau`` is limited to 0x6072 (per mille of
the rated torque 0x6076). With the integral at 0 this is the impedance ``kp = Kpos * Kvel``,
``kd = Kvel``. The registers map to the loop as the drive realises them:

- ``Kvel = vel_reg * 0.1063 * (Kt * gear) / (0.132e-3 * 50) * 0.7`` (0.7 = realised/nominal, the
  harmonic-drive efficiency seen in load tests; the master's conversion divides it back out),
- ``Kpos = pos_reg / 51.47`` (1/s), so ``kp = pos_reg / 51.47 * Kvel``,
- ``Ki = integral * 0.1063 * (Kt * gear) / (0.132e-3 * 50) * 0.7`` (Nm/rad; model units).

The object dictionary follows ZeroErr's EDS V1.5: the loop gains 0x2381:01/:02 and 0x2382:01/:02 are
UNSIGNED16 (``gain_bytes`` 4 presents the u32 variant one public host reads), sizes are enforced as a CoE
stack that checks them does (a write of another length aborts 0x06070010), 0x1003 keeps 4 errors, 0x6502
reads 0x38D, 0x6076 (rated torque, u32 mN*m) is read-only and PDO-mappable, 0x60B2 takes +-3000 per mille,
0x6065 is INTEGER32. At power up 0x1600 maps 607A/60FE/6040 and 0x1A00 6064/60FD/6041 (ZeroErr's
description); a master maps its own layout in PRE-OP. The gate 0x2383 is not in the EDS; it is UDINT here,
as ZeroErr's parameter table lists it.

While the gate 0x2383 is 0 the drive runs its factory gains (FACTORY_* below: realised kp 300 Nm/rad,
kd 9.97 Nm*s/rad, no integral); writes to 0x2381/0x2382 then succeed but are ignored and read back the
factory values. With the gate at 1 the written registers are stored and used; setting it back to 0
restores the factory values.

A disabled drive (any state but operation enabled in CSP) holds its joint with the holding brake.
Following error: ``|0x607A - 0x6064|`` above the window 0x6065 for longer than 0x6066 ms while
enabled -> fault 0x8500. Statusword: 0x1637 (5687) operation enabled in CSP, 0x1208 (4616) fault in CSP.
"""

from __future__ import annotations

import math
from enum import IntEnum

from humanoid_prime.config.hardware import DEFAULT_GEAR, DEFAULT_KT_NM_PER_MA
from humanoid_prime.drivers.erob import objects as obj
from humanoid_prime.drivers.erob.constants import (
    COUNTS_PER_RAD,
    MIN_CYCLE_S,
    MODE_CSP,
    PRODUCT_CODE,
    RATED_TORQUE_NM,
    VENDOR_ID,
)
from humanoid_prime.drivers.erob.gains import (
    KD_PER_VEL_REG_NM_S_PER_RAD,
    REFERENCE_KT_GEAR_NM_PER_MA,
    REGISTER_MAX,
    ErobRegisters,
    registers_to_gains,
)
from humanoid_prime.drivers.ethercat.wire import ABORT_VALUE_RANGE
from humanoid_prime.virtual.ring.od import (
    OBJECT_ARRAY,
    OBJECT_RECORD,
    PDO_RX,
    PDO_TX,
    READ_ONLY,
    Entry,
    ObjectDictionary,
    SdoAbort,
)

REALISED_EFFICIENCY = 0.7  # realised / nominal stiffness of the eRob harmonic drive (DESIGN §2)
FACTORY_VEL_REG = 134  # 134 * 0.1063 * 0.7 = 9.97 Nm*s/rad
FACTORY_POS_REG = 1549  # 1549 / 51.47 * 9.97 = 300.1 Nm/rad
FACTORY_INTEGRAL = 0
FOLLOWING_ERROR_WINDOW_COUNTS = round(0.5 * COUNTS_PER_RAD)  # 0.5 rad
FOLLOWING_ERROR_TIMEOUT_MS = 10
MAX_TORQUE_PER_MILLE = 1500
DEVICE_TYPE_SERVO = 0x00020192  # CiA402 profile, servo drive
SUPPORTED_MODES = 0x0000038D  # 0x6502: pp, pv, tq, csp, csv, cst (ZeroErr EDS V1.5 reads 909)
REVISION = 0x00000001

ERROR_COMMUNICATION = 0xA000
ERROR_FOLLOWING = 0x8500
ERROR_VELOCITY = 0x8400
ERROR_HEARTBEAT = 0x8130
ERROR_BATTERY_LOW = 0x730F
ERROR_HISTORY_LENGTH = 4  # 0x1003 sub-entries (ZeroErr EDS V1.5)
GAIN_FORMATS = {2: "H", 4: "I"}  # loop-gain register width in bytes -> object type


class Cia402State(IntEnum):
    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT = 6


# Statusword low bits per state (CiA402), with voltage enabled (bit 4) and remote (bit 9) as the eRob
# reports them; CSP adds bit 12 (drive follows the command) and operation enabled bit 10.
_STATUS_BITS = {
    Cia402State.NOT_READY_TO_SWITCH_ON: 0x0200,
    Cia402State.SWITCH_ON_DISABLED: 0x0250,
    Cia402State.READY_TO_SWITCH_ON: 0x0231,
    Cia402State.SWITCHED_ON: 0x0233,
    Cia402State.OPERATION_ENABLED: 0x0637,
    Cia402State.QUICK_STOP_ACTIVE: 0x0217,
    Cia402State.FAULT: 0x0208,
}
STATUSWORD_FOLLOWS_COMMAND = 0x1000
STATUSWORD_FOLLOWING_ERROR = 0x2000


def physical_gains(pos_reg: int, vel_reg: int, integral: int, *, kt: float = DEFAULT_KT_NM_PER_MA,
                   gear: float = DEFAULT_GEAR) -> tuple[float, float, float]:
    """(kp Nm/rad, kd Nm*s/rad, ki Nm/rad) the drive realises from its registers; the integral register
    steps like the velocity gain's."""
    kp, kd = registers_to_gains(ErobRegisters(pos_reg, vel_reg, integral), kt=kt, gear=gear,
                                transmission_efficiency=REALISED_EFFICIENCY)
    per_step = KD_PER_VEL_REG_NM_S_PER_RAD * (kt * gear) / REFERENCE_KT_GEAR_NM_PER_MA * REALISED_EFFICIENCY
    return kp, kd, integral * per_step


# The objects with more than one entry, as the SDO information service names them.
OBJECT_NAMES = (
    (obj.ERROR_HISTORY, "Pre-defined error field", OBJECT_ARRAY),
    (obj.IDENTITY, "Identity object", OBJECT_RECORD),
    (obj.SM_COMM_TYPE, "Sync manager communication type", OBJECT_ARRAY),
    (obj.SYNC_OUTPUT, "SM output parameter", OBJECT_RECORD),
    (obj.SYNC_INPUT, "SM input parameter", OBJECT_RECORD),
    (obj.VEL_LOOP_GAIN[0], "Velocity Loop Gains", OBJECT_ARRAY),
    (obj.POS_LOOP_GAIN[0], "Position Loop Gains", OBJECT_ARRAY),
    (obj.RXPDO_MAP, "RxPDO 1 mapping", OBJECT_RECORD),
    (obj.TXPDO_MAP, "TxPDO 1 mapping", OBJECT_RECORD),
    (obj.RXPDO_ASSIGN, "RxPDO assign", OBJECT_ARRAY),
    (obj.TXPDO_ASSIGN, "TxPDO assign", OBJECT_ARRAY),
)


class ErobDrive:
    """One eRob: its object dictionary, its CiA402 state and its CSP loop."""

    def __init__(self, serial: int = 0, *, kt: float = DEFAULT_KT_NM_PER_MA, gear: float = DEFAULT_GEAR,
                 gain_bytes: int = 2, rated_torque_mnm: int = round(RATED_TORQUE_NM * 1000)) -> None:
        if gain_bytes not in GAIN_FORMATS:
            raise ValueError(f"gain registers are 2 or 4 bytes, got {gain_bytes}")
        self.serial = serial
        self.kt = kt
        self.gear = gear
        self.gain_format = GAIN_FORMATS[gain_bytes]
        self.rated_torque_nm = rated_torque_mnm / 1000.0
        self.state = Cia402State.SWITCH_ON_DISABLED
        self.latched_faults: set[int] = set()
        self.last_gain_write_applied = True
        self._last_controlword = 0
        self._integral_nm = 0.0
        self._following_error_s = 0.0
        self._following_error_flag = False
        self.torque_nm = 0.0
        self.od = ObjectDictionary()
        self._build_od(serial)
        self._kp, self._kd, self._ki = physical_gains(FACTORY_POS_REG, FACTORY_VEL_REG, FACTORY_INTEGRAL,
                                                      kt=kt, gear=gear)
        self.update_feedback(0.0, 0.0)

    # ---- object dictionary --------------------------------------------------------------------------------
    def _build_od(self, serial: int) -> None:
        od = self.od
        add = od.add
        add(Entry(obj.DEVICE_TYPE, 0, "device type", "I", DEVICE_TYPE_SERVO, READ_ONLY))
        self._error_register = add(Entry(0x1001, 0, "error register", "B", 0, READ_ONLY))
        self._history_count = add(Entry(obj.ERROR_HISTORY, 0, "number of errors", "B", 0,
                                        on_write=self._clear_history))
        self._history = [add(Entry(obj.ERROR_HISTORY, i, f"standard error field {i}", "I", 0, READ_ONLY))
                         for i in range(1, ERROR_HISTORY_LENGTH + 1)]
        add(Entry(0x1008, 0, "manufacturer device name", "s", "eRob rotary actuator, CiA402 (emulated)", READ_ONLY))
        add(Entry(0x1009, 0, "manufacturer hardware version", "s", "emulated", READ_ONLY))
        add(Entry(0x100A, 0, "manufacturer software version", "s", "humanoid_prime emulator", READ_ONLY))
        add(Entry(obj.IDENTITY, 0, "number of entries", "B", 4, READ_ONLY))
        for sub, name, value in ((1, "vendor id", VENDOR_ID), (2, "product code", PRODUCT_CODE),
                                 (3, "revision", REVISION), (4, "serial number", serial)):
            add(Entry(obj.IDENTITY, sub, name, "I", value, READ_ONLY))
        add(Entry(obj.SM_COMM_TYPE, 0, "number of SyncManagers", "B", 4, READ_ONLY))
        for sub, kind in ((1, 1), (2, 2), (3, 3), (4, 4)):
            add(Entry(obj.SM_COMM_TYPE, sub, f"SM{sub - 1} type", "B", kind, READ_ONLY))
        for index, sub, name in ((obj.SYNC_OUTPUT, 0, "outputs"), (obj.SYNC_INPUT, 0, "inputs")):
            add(Entry(index, sub, f"SM {name} parameter entries", "B", 5, READ_ONLY))
            add(Entry(index, 1, "synchronisation type", "H", 2))  # 2 = DC SYNC0
            add(Entry(index, 2, "cycle time", "I", 0, READ_ONLY))
            add(Entry(index, 3, "shift time", "I", 0, READ_ONLY))
            add(Entry(index, 4, "supported synchronisation types", "H", 0x0005, READ_ONLY))
            add(Entry(index, 5, "minimum cycle time", "I", round(MIN_CYCLE_S * 1e9), READ_ONLY))

        self.controlword = add(Entry(obj.CONTROLWORD, 0, "controlword", "H", 0, pdo=PDO_RX,
                                     on_write=self._sdo_output_write))
        self.statusword = add(Entry(obj.STATUSWORD, 0, "statusword", "H", 0, READ_ONLY, pdo=PDO_TX))
        self.error_code = add(Entry(obj.ERROR_CODE, 0, "error code", "H", 0, READ_ONLY, pdo=PDO_TX))
        self.mode = add(Entry(obj.MODE_OF_OPERATION, 0, "modes of operation", "b", 0, pdo=PDO_RX,
                              on_write=self._sdo_output_write))
        self.mode_display = add(Entry(obj.MODE_DISPLAY, 0, "modes of operation display", "b", 0, READ_ONLY,
                                      pdo=PDO_TX))
        self.position_actual = add(Entry(obj.POSITION_ACTUAL, 0, "position actual value", "i", 0, READ_ONLY,
                                         pdo=PDO_TX))
        self.velocity_actual = add(Entry(obj.VELOCITY_ACTUAL, 0, "velocity actual value", "i", 0, READ_ONLY,
                                         pdo=PDO_TX))
        self.torque_actual = add(Entry(obj.TORQUE_ACTUAL, 0, "torque actual value", "h", 0, READ_ONLY,
                                       pdo=PDO_TX))
        add(Entry(obj.RATED_TORQUE, 0, "motor rated torque (mNm)", "I", round(self.rated_torque_nm * 1000),
                  READ_ONLY, pdo=PDO_TX))
        self.following_window = add(Entry(obj.FOLLOWING_ERROR_WINDOW, 0, "following error window", "i",
                                          FOLLOWING_ERROR_WINDOW_COUNTS, minimum=0))
        self.following_timeout = add(Entry(0x6066, 0, "following error time out (ms)", "H",
                                           FOLLOWING_ERROR_TIMEOUT_MS))
        self.max_torque = add(Entry(0x6072, 0, "max torque (per mille)", "H", MAX_TORQUE_PER_MILLE))
        self.target_position = add(Entry(obj.TARGET_POSITION, 0, "target position", "i", 0, pdo=PDO_RX))
        self.following_error = add(Entry(0x60F4, 0, "following error actual value", "i", 0, READ_ONLY,
                                         pdo=PDO_TX))
        self.velocity_offset = add(Entry(obj.VELOCITY_OFFSET, 0, "velocity offset", "i", 0, pdo=PDO_RX))
        limit = obj.TORQUE_OFFSET_LIMIT_PER_MILLE
        self.torque_offset = add(Entry(obj.TORQUE_OFFSET, 0, "torque offset", "h", 0, pdo=PDO_RX,
                                       minimum=-limit, maximum=limit))
        add(Entry(obj.DIGITAL_INPUTS, 0, "digital inputs", "I", 0, READ_ONLY, pdo=PDO_TX))
        add(Entry(*obj.DIGITAL_OUTPUTS, "digital outputs", "I", 0, pdo=PDO_RX))
        add(Entry(obj.SUPPORTED_DRIVE_MODES, 0, "supported drive modes", "I", SUPPORTED_MODES, READ_ONLY))

        gain = self.gain_format  # names as ZeroErr's EDS V1.5 gives them
        add(Entry(obj.VEL_LOOP_GAIN[0], 0, "Number of entries", "B", 2, READ_ONLY))
        self.vel_reg = add(Entry(*obj.VEL_LOOP_GAIN, "Velocity Loop Proportional Gain", gain, FACTORY_VEL_REG,
                                 maximum=REGISTER_MAX, on_write=self._gain_write))
        self.integral_reg = add(Entry(*obj.VEL_LOOP_INTEGRAL, "Velocity Loop integral Gain", gain, FACTORY_INTEGRAL,
                                      maximum=REGISTER_MAX, on_write=self._gain_write))
        add(Entry(obj.POS_LOOP_GAIN[0], 0, "Number of entries", "B", 2, READ_ONLY))
        self.pos_reg = add(Entry(*obj.POS_LOOP_GAIN, "Position Loop Proportional Gain", gain, FACTORY_POS_REG,
                                 maximum=REGISTER_MAX, on_write=self._gain_write))
        add(Entry(*obj.POS_LOOP_INTEGRAL, "Position Loop integral Gain", gain, 0, maximum=REGISTER_MAX))
        self.gate = add(Entry(*obj.BUS_GAIN_GATE, "bus regulation of PID switch", "I", 0,
                              on_write=self._gate_write))

        for assign, pdo_index, entries in ((obj.RXPDO_ASSIGN, obj.RXPDO_MAP, obj.POWER_UP_RXPDO),
                                           (obj.TXPDO_ASSIGN, obj.TXPDO_MAP, obj.POWER_UP_TXPDO)):
            add(Entry(pdo_index, 0, "number of mapped objects", "B", len(entries)))
            for sub in range(1, 17):
                value = entries[sub - 1].mapping if sub <= len(entries) else 0
                add(Entry(pdo_index, sub, f"mapped object {sub}", "I", value))
            add(Entry(assign, 0, "number of assigned PDOs", "B", 1))
            add(Entry(assign, 1, "assigned PDO", "H", pdo_index))
        for index, name, code in OBJECT_NAMES:
            od.name_object(index, name, code)

    def _clear_history(self, entry: Entry, value: int | str) -> int:
        if value != 0:
            raise SdoAbort(ABORT_VALUE_RANGE, "only 0 may be written to 0x1003:00 (clears the history)")
        for field in self._history:
            field.value = 0
        return 0

    def _sdo_output_write(self, entry: Entry, value: int | str) -> int | str:
        entry.value = value
        self.process_outputs()
        return value

    def _gain_write(self, entry: Entry, value: int | str) -> int | str:
        self.last_gain_write_applied = self.gate.value == 1
        if not self.last_gain_write_applied:
            return entry.value  # silently ignored: the factory value stays
        entry.value = value
        self._refresh_gains()
        return value

    def _gate_write(self, entry: Entry, value: int | str) -> int | str:
        if value not in (0, 1):
            raise SdoAbort(ABORT_VALUE_RANGE, "0x2383 takes 0 (factory gains) or 1 (bus gains)")
        self.last_gain_write_applied = True
        entry.value = value
        if value == 0:
            self.pos_reg.value = FACTORY_POS_REG
            self.vel_reg.value = FACTORY_VEL_REG
            self.integral_reg.value = FACTORY_INTEGRAL
        self._refresh_gains()
        return value

    def _refresh_gains(self) -> None:
        self._kp, self._kd, self._ki = physical_gains(int(self.pos_reg.value), int(self.vel_reg.value),
                                                      int(self.integral_reg.value), kt=self.kt, gear=self.gear)

    @property
    def gains(self) -> tuple[float, float, float]:
        """(kp, kd, ki) the loop uses now, in SI."""
        return self._kp, self._kd, self._ki

    # ---- CiA402 ---------------------------------------------------------------------------------------------
    @property
    def braked(self) -> bool:
        return not (self.state == Cia402State.OPERATION_ENABLED and self.mode_display.value == MODE_CSP)

    @property
    def csp_enabled(self) -> bool:
        return not self.braked

    def process_outputs(self) -> None:
        """React to the controlword and mode just received (process data or SDO)."""
        if self.mode.value in (0, MODE_CSP):
            self.mode_display.value = self.mode.value
        cw = int(self.controlword.value)
        previous = self._last_controlword
        self._last_controlword = cw
        state = self.state
        if state == Cia402State.FAULT:
            if cw & 0x80 and not previous & 0x80 and not self.latched_faults:
                self.state = Cia402State.SWITCH_ON_DISABLED
                self.error_code.value = 0
                self._error_register.value = 0
            return
        if cw & 0x80:
            return
        disable_voltage = not cw & 0x02
        quick_stop = cw & 0x06 == 0x02
        shutdown = cw & 0x07 == 0x06
        switch_on = cw & 0x0F == 0x07
        enable = cw & 0x0F == 0x0F
        new = state
        if state == Cia402State.SWITCH_ON_DISABLED:
            if shutdown:
                new = Cia402State.READY_TO_SWITCH_ON
        elif state == Cia402State.READY_TO_SWITCH_ON:
            if disable_voltage or quick_stop:
                new = Cia402State.SWITCH_ON_DISABLED
            elif switch_on:
                new = Cia402State.SWITCHED_ON
            elif enable:
                new = Cia402State.OPERATION_ENABLED
        elif state == Cia402State.SWITCHED_ON:
            if disable_voltage or quick_stop:
                new = Cia402State.SWITCH_ON_DISABLED
            elif shutdown:
                new = Cia402State.READY_TO_SWITCH_ON
            elif enable:
                new = Cia402State.OPERATION_ENABLED
        elif state == Cia402State.OPERATION_ENABLED:
            if disable_voltage:
                new = Cia402State.SWITCH_ON_DISABLED
            elif quick_stop:
                new = Cia402State.QUICK_STOP_ACTIVE
            elif shutdown:
                new = Cia402State.READY_TO_SWITCH_ON
            elif switch_on:
                new = Cia402State.SWITCHED_ON
        elif state == Cia402State.QUICK_STOP_ACTIVE and disable_voltage:
            new = Cia402State.SWITCH_ON_DISABLED
        if new == Cia402State.OPERATION_ENABLED and state != new:
            self._integral_nm = 0.0
            self._following_error_s = 0.0
        self.state = new

    def fault(self, code: int, *, latched: bool = False) -> None:
        """Enter FAULT with ``code`` in 0x603F and at the top of the 0x1003 history."""
        if latched:
            self.latched_faults.add(code)
        self.state = Cia402State.FAULT
        self.error_code.value = code
        self._error_register.value = 0x01
        for newer, older in zip(self._history[-2::-1], self._history[:0:-1], strict=True):
            older.value = newer.value
        self._history[0].value = code
        self._history_count.value = min(int(self._history_count.value) + 1, ERROR_HISTORY_LENGTH)
        self.torque_nm = 0.0

    def clear_latched(self) -> None:
        self.latched_faults.clear()

    @property
    def error_history(self) -> list[int]:
        return [int(f.value) & 0xFFFF for f in self._history[:int(self._history_count.value)]]

    # ---- control loop -----------------------------------------------------------------------------------
    def step(self, q: float, qd: float, dt: float) -> float:
        """Advance the drive by ``dt`` at joint state (q rad, qd rad/s); returns the motor torque (Nm)."""
        if self.state == Cia402State.QUICK_STOP_ACTIVE:
            self.state = Cia402State.SWITCH_ON_DISABLED
        if self.braked:
            self.torque_nm = 0.0
            self._following_error_flag = False
            return 0.0
        target = int(self.target_position.value)
        error_counts = target - round(q * COUNTS_PER_RAD)
        if abs(error_counts) > int(self.following_window.value):
            self._following_error_s += dt
            self._following_error_flag = True
            if self._following_error_s * 1000.0 > int(self.following_timeout.value):
                self.fault(ERROR_FOLLOWING)
                return 0.0
        else:
            self._following_error_s = 0.0
            self._following_error_flag = False
        limit = int(self.max_torque.value) / 1000.0 * self.rated_torque_nm
        velocity_command = (self._kp / self._kd if self._kd > 0 else 0.0) * (target / COUNTS_PER_RAD - q)
        velocity_command += int(self.velocity_offset.value) / COUNTS_PER_RAD
        velocity_error = velocity_command - qd
        if self._ki > 0:
            self._integral_nm = min(max(self._integral_nm + self._ki * velocity_error * dt, -limit), limit)
        else:
            self._integral_nm = 0.0
        tau = self._kd * velocity_error + self._integral_nm
        offset = min(max(int(self.torque_offset.value), -obj.TORQUE_OFFSET_LIMIT_PER_MILLE),
                     obj.TORQUE_OFFSET_LIMIT_PER_MILLE)  # a process-data value beyond the range is held at it
        tau += offset / 1000.0 * self.rated_torque_nm
        tau = min(max(tau, -limit), limit)
        self.torque_nm = tau
        return tau

    def update_feedback(self, q: float, qd: float) -> None:
        """Refresh the input objects (position, velocity, torque, statusword) from the joint state."""
        position = round(q * COUNTS_PER_RAD)
        self.position_actual.value = _clamp_i32(position)
        self.velocity_actual.value = _clamp_i32(round(qd * COUNTS_PER_RAD))
        per_mille = round(self.torque_nm / self.rated_torque_nm * 1000.0) if math.isfinite(self.torque_nm) else 0
        self.torque_actual.value = min(max(per_mille, -0x8000), 0x7FFF)
        enabled = self.state == Cia402State.OPERATION_ENABLED
        self.following_error.value = _clamp_i32(int(self.target_position.value) - position) if enabled else 0
        status = _STATUS_BITS[self.state]
        if self.mode_display.value == MODE_CSP and self.state in (Cia402State.OPERATION_ENABLED, Cia402State.FAULT):
            status |= STATUSWORD_FOLLOWS_COMMAND
        if self._following_error_flag:
            status |= STATUSWORD_FOLLOWING_ERROR
        self.statusword.value = status


def _clamp_i32(value: int) -> int:
    return min(max(value, -0x80000000), 0x7FFFFFFF)
