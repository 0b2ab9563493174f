"""``EthercatSystem``: the ten eRob arm joints as one hardware component, CiA402 CSP over an EtherCAT master.

Calibration is applied exactly as the C++ stack applies it: at configure time the calibration is folded
into one per-slave config per joint (``fold.py``, in memory), each is validated with
``parse_slave_config``, and every channel converts with ``value = factor * x + offset`` (DESIGN §2).

Per tick, ``read`` collects the frame and converts position, velocity and effort into the joint frame;
``write`` converts the command into CSP targets and sends the frame. While a joint's commanded stiffness
is zero, or its drive is not operation-enabled, its CSP target follows the actual position, so a limp arm
never accumulates following error (0x8500) and enabling never jumps. A NaN position means no command:
the drive keeps its last target and holds there with its own gains (e.g. the joints nobody sweeps during
calibration). Both are allocation-free: every
array is preallocated and the process image is reached through views bound once.

Safety flags: ``ethercat/wkc`` (working counter mismatch for ``wkc_tolerance_cycles`` cycles in a row),
``ethercat/ring<N>/lost`` (slave not in OP or not answering), ``ethercat/ring<N>/fault`` (drive fault:
decoded statusword and error code), and the warning ``ethercat/ring<N>/rated_torque`` (the drive's
0x6076 could not be read at bring-up, so its efforts use the nominal rated torque).

Efforts are per mille of each drive's rated torque, read from 0x6076 in PRE-OP: the fold's factors assume
the nominal figure (the C++ stack cannot read it), and are rescaled here once the drive has said its own.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from humanoid_prime.config.calibration import Calibration
from humanoid_prime.config.description import ETHERCAT_BLOCK
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import Level
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.erob.cia402 import (
    BRINGUP_TRANSIENT_FAULT,
    DISABLE_VOLTAGE,
    ERROR_HINTS,
    FAULT_PATTERN,
    FAULT_RESET,
    OPERATION_ENABLED_PATTERN,
    describe_al_state,
    describe_error,
    drive_state,
    enable_step,
)
from humanoid_prime.drivers.erob.constants import MODE_CSP, RATED_TORQUE_NM
from humanoid_prime.drivers.erob.objects import (
    POSITION_ACTUAL,
    TARGET_POSITION,
    TORQUE_ACTUAL,
    TORQUE_OFFSET,
    TORQUE_OFFSET_LIMIT_PER_MILLE,
    VELOCITY_ACTUAL,
    VELOCITY_OFFSET,
)
from humanoid_prime.drivers.ethercat.fold import check_foldable, fold_slave_config, write_folded_configs
from humanoid_prime.drivers.ethercat.master import (
    RX_DTYPE,
    TX_DTYPE,
    BringupReport,
    EthercatMaster,
    ExpectedSlave,
    check_ring,
)
from humanoid_prime.drivers.ethercat.slave_config import Channel, SlaveConfig, parse_slave_config
from humanoid_prime.errors import ConfigError, PrimeError


def _pdo_limits(*fields: str) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of the mapped integer types of ``fields``, one row each, as floats for np.clip."""
    ranges = [np.iinfo(RX_DTYPE[f]) for f in fields]
    return (np.array([[r.min] for r in ranges], float), np.array([[r.max] for r in ranges], float))


def _round_clamp(raw: np.ndarray, limits: tuple[np.ndarray, np.ndarray], out: np.ndarray) -> None:
    """Round half up and clamp to the PDO type into ``out`` (as ``Channel.command_raw`` does), in place."""
    np.add(raw, 0.5, out=raw)
    np.floor(raw, out=raw)
    np.clip(raw, limits[0], limits[1], out=raw)
    np.copyto(out, raw, casting="unsafe")


_TARGET_LIMITS = tuple(row[0] for row in _pdo_limits("target_position"))
_FF_LIMITS = _pdo_limits("velocity_offset", "torque_offset")  # one row each
# 0x60B2 accepts +-3000 per mille of the rated torque (ZeroErr EDS V1.5), narrower than its INTEGER16
_FF_LIMITS[0][1], _FF_LIMITS[1][1] = -TORQUE_OFFSET_LIMIT_PER_MILLE, TORQUE_OFFSET_LIMIT_PER_MILLE
_OPERATION_ENABLED_MASK, _OPERATION_ENABLED = OPERATION_ENABLED_PATTERN
_FAULT_MASK, _FAULT = FAULT_PATTERN
_MIT = ("position", "velocity", "effort")
_STATE_OBJECTS = (POSITION_ACTUAL, VELOCITY_ACTUAL, TORQUE_ACTUAL)
_COMMAND_OBJECTS = (TARGET_POSITION, VELOCITY_OFFSET, TORQUE_OFFSET)


def _controlword_table(auto_fault_reset: bool) -> np.ndarray:
    """Controlword for every value of ``statusword & 0x7F`` (the bits the CiA402 state depends on)."""
    table = np.array([enable_step(sw) for sw in range(0x80)], dtype=np.uint16)
    if not auto_fault_reset:
        table[table == FAULT_RESET] = DISABLE_VOLTAGE
    return table


class EthercatSystem(HardwareComponent):
    """The eRob joints of ``robot`` (canonical order), each bound to its ring position."""

    def __init__(self, robot: Robot, calibration: Calibration, *, update_rate: float,
                 bringup_rate: float = 1000.0, master: EthercatMaster | None = None,
                 interface: str | None = None, config_dir: str | Path | None = None,
                 enable_timeout_s: float = 5.0, wkc_tolerance_cycles: int = 3,
                 name: str = ETHERCAT_BLOCK) -> None:
        hw = robot.hardware
        super().__init__(name, robot, hw.erob_joints)
        self.robot = robot
        self.calibration = calibration
        self.update_rate = update_rate
        self.bringup_rate = bringup_rate
        self.master = master
        self.interface = interface or hw.ethercat.interface
        self.config_dir = Path(config_dir) if config_dir is not None else None
        self.enable_timeout_s = enable_timeout_s
        # A single lost frame is counted, not flagged: the drives hold their last target for one cycle.
        self.wkc_tolerance_cycles = wkc_tolerance_cycles
        self.wkc_errors = 0
        self._wkc_bad_cycles = 0
        self.ring = np.array([hw.erob_slaves[j] for j in self.joints], dtype=np.intp)
        self.slave_configs: dict[str, SlaveConfig] = {}
        self.expected: tuple[ExpectedSlave, ...] = ()
        self.bringup: BringupReport | None = None
        n = len(self.joints)
        # factor/offset per MIT interface (rows position, velocity, effort), joint order
        self.state_factor = np.ones((3, n))
        self.state_offset = np.zeros((3, n))
        self.command_factor = np.ones((3, n))
        self.command_offset = np.zeros((3, n))
        # the rated torque each drive reported (0x6076), NaN where it could not be read and the fold's
        # nominal figure scales the efforts instead
        self.rated_torque_nm = np.full(n, math.nan)
        self._fold_effort = (np.ones(n), np.ones(n))  # the fold's effort factors (state, command), nominal torque
        self._cw_table = _controlword_table(False)  # a fault latches (see _enable for the one exception)
        self._reset_requested = False
        # raw process values in joint order
        self._rec = np.zeros(n, TX_DTYPE)  # the inputs of this component's slaves, joint order
        self._rec_pos, self._rec_vel, self._rec_tq = (self._rec[f] for f in
                                                      ("position_actual", "velocity_actual", "torque_actual"))
        self._rec_sw, self._rec_err = self._rec["statusword"], self._rec["error_code"]
        self._raw = np.zeros((3, n))  # position, velocity, effort as raw counts / per mille
        self._raw_pos, self._raw_vel, self._raw_tq = self._raw
        self._sw7 = np.zeros(n, np.uint16)
        self._cw = np.zeros(n, np.uint16)
        self._cw_prev = np.zeros(n, np.uint16)
        self._enabled = np.zeros(n, dtype=bool)
        self._was_enabled = np.zeros(n, dtype=bool)  # in the last frame read
        # Drives that left operation enabled mid-run without a fault (their slave lost power or link and came
        # back in switch-on disabled): held disabled until the operator's reset, because enabling one on its own
        # would drive the joint, which hung limp meanwhile, straight to the active mode's target.
        self._held_off = np.zeros(n, dtype=bool)
        self._dropped = np.zeros(n, dtype=bool)
        self._held_off_seen = np.zeros(n, dtype=bool)
        self._fault = np.zeros(n, dtype=bool)
        self._follow = np.zeros(n, dtype=bool)
        self._mask = np.zeros(n, dtype=bool)  # scratch masks
        self._scratch = np.zeros(n, dtype=bool)
        self._mask2 = np.zeros((2, n), dtype=bool)
        self._x = np.zeros(n)  # scratch, joint frame
        self._t = np.zeros(n)  # scratch, raw
        self._x2 = np.zeros((2, n))  # velocity and effort feed-forward
        self._x2_vel, self._x2_eff = self._x2
        self._ff_factor, self._ff_offset = self.command_factor[1:], self.command_offset[1:]
        self._x3 = np.zeros((3, n))  # position, velocity, effort state
        self._kp = np.zeros(n)
        self._i32 = np.zeros(n, np.int32)  # the rounded raw value before it goes into the process image
        self._i32_2 = np.zeros((2, n), np.int32)
        self._ff_vel, self._ff_tq = self._i32_2
        self._held = np.zeros(n)  # the last CSP target sent (raw), what a NaN position command keeps
        self._wkc_flagged = False
        self._fault_seen: tuple = ()
        self._health_seen = -1

    # ---------------------------------------------------------------------------- lifecycle
    def on_configure(self) -> None:
        """Fold the calibration into one per-slave config per joint, in memory (``config_dir`` also gets the
        files, for the C++ stack and for people), take every channel's factor and offset from it, then open
        the master and check the ring against the hardware file."""
        check_foldable(self.robot, self.calibration)
        if self.config_dir is not None:
            write_folded_configs(self.robot, self.calibration, self.config_dir)
        source = f"the calibration fold of {self.calibration.path or 'the calibration in memory'}"
        expected, auto_reset = [], []
        for k, joint in enumerate(self.joints):
            spec = self.robot.joints[int(self.indices[k])]
            config = parse_slave_config(fold_slave_config(spec, self.calibration.joints[joint]),
                                        f"{source} ({joint})")
            self.slave_configs[joint] = config
            for row, interface in enumerate(_MIT):
                state = _checked(config, config.state(interface), _STATE_OBJECTS[row])
                command = _checked(config, config.command(interface), _COMMAND_OBJECTS[row])
                self.state_factor[row, k], self.state_offset[row, k] = state.factor, state.offset
                self.command_factor[row, k], self.command_offset[row, k] = command.factor, command.offset
            auto_reset.append(config.auto_fault_reset)
            expected.append(ExpectedSlave(int(self.ring[k]), joint, config.vendor_id, config.product_id))
        self._fold_effort = (self.state_factor[2].copy(), self.command_factor[2].copy())
        self.expected = tuple(sorted(expected, key=lambda e: e.position))
        self._cw_table = _controlword_table(all(auto_reset))  # fault reset only if every config asks for it
        if self.master is None:
            from humanoid_prime.drivers.ethercat.soem_master import SoemMaster

            self.master = SoemMaster(self.interface, update_rate=self.update_rate,
                                     bringup_rate=self.bringup_rate)
        try:
            check_ring(self.master.open(), self.expected, self.master.interface)
        except BaseException:
            self.master.close()
            raise

    def on_activate(self) -> None:
        """Bring the ring to OP (once) and enable every drive; the master's keeper feeds the outputs from
        then until the controller manager's first tick."""
        master = self._master()
        if not master.operational:
            self.bringup = master.start(self.expected)
            self._bind_views()
            self._scale_efforts()
        self._enable()

    def _scale_efforts(self) -> None:
        """Scale 0x6077/0x60B2 with the rated torque each drive reported (the fold assumes the nominal one);
        a drive whose 0x6076 could not be read keeps the nominal scale, with a warning."""
        master = self._master()
        state_fold, command_fold = self._fold_effort
        for k, joint in enumerate(self.joints):
            position = int(self.ring[k])
            rated = float(master.rated_torque_nm[position]) if position < len(master.rated_torque_nm) else math.nan
            self.rated_torque_nm[k] = rated
            key = f"ethercat/ring{position}/rated_torque"
            if math.isfinite(rated):
                self.state_factor[2, k] = state_fold[k] * rated / RATED_TORQUE_NM
                self.command_factor[2, k] = command_fold[k] * RATED_TORQUE_NM / rated
                self.clear_flag(key)
            else:
                self.state_factor[2, k], self.command_factor[2, k] = state_fold[k], command_fold[k]
                why = master.rated_torque_problems.get(position, "this master does not read it")
                self.set_flag(key, f"{joint} (ring {position}): rated torque (0x6076) unknown ({why}); efforts "
                                   f"scaled with the nominal {RATED_TORQUE_NM:g} N*m", Level.WARN)

    def on_deactivate(self) -> None:
        """Disable every drive (its brake holds the joint); the ring stays in OP, the keeper feeds it."""
        master = self._master()
        if master.operational:
            self._out_cw[:] = DISABLE_VOLTAGE
            np.copyto(self._out_target, self._in_pos)
            master.exchange()

    def on_shutdown(self) -> None:
        if self.master is not None:
            self.master.close()

    @property
    def enabled(self) -> np.ndarray:
        """Per joint: its drive reported operation enabled in the last frame read (copy)."""
        return self._enabled.copy()

    @property
    def faulted(self) -> np.ndarray:
        """Per joint: its drive reported fault in the last frame read (copy)."""
        return self._fault.copy()

    @property
    def bus_ready(self) -> bool:
        """True once every slave is in OP and joint states flow: SDOs (gains) may go out."""
        return self.master is not None and self.master.sdo_ready

    def _master(self) -> EthercatMaster:
        if self.master is None:
            raise PrimeError(f"{self.name}: not configured")
        return self.master

    def _bind_views(self) -> None:
        master = self._master()
        inputs, outputs = master.inputs, master.outputs
        self._inputs = inputs
        self._in_pos = inputs["position_actual"]
        self._out_cw = outputs["controlword"]
        self._out_target = outputs["target_position"]
        self._out_vel = outputs["velocity_offset"]
        self._out_tq = outputs["torque_offset"]
        self._out_mode = outputs["mode_of_operation"]

    def _enable(self) -> None:
        """CiA402 enable at the bring-up rate: target on the actual position first, then step to enabled.

        A fault latches (it waits for the operator's reset), with one exception: the EtherCAT communication
        fault (0xA000) a drive may raise while DC locks during bring-up is reset here, so it clears by itself.
        Enabling ends when every drive is enabled or latched in another fault (flagged by ``read``)."""
        master = self._master()
        deadline = time.monotonic() + self.enable_timeout_s
        rate = Rate(self.bringup_rate)
        n = len(self.joints)
        transient, latched = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        while True:
            rate.wait()
            self._gather()
            np.equal(self._rec_err, BRINGUP_TRANSIENT_FAULT, out=transient)
            np.logical_and(transient, self._fault, out=transient)
            np.logical_not(transient, out=latched)
            np.logical_and(latched, self._fault, out=latched)
            if (self._enabled | latched).all():
                np.copyto(self._was_enabled, self._enabled)
                np.take(self._out_target, self.ring, out=self._i32)
                np.copyto(self._held, self._i32)  # a NaN command holds the position the drive was enabled at
                return
            np.copyto(self._out_target, self._in_pos)
            self._out_vel[:] = 0
            self._out_tq[:] = 0
            self._out_mode[:] = MODE_CSP
            self._step_controlwords(transient)
            master.exchange()
            if time.monotonic() > deadline:
                self._gather()
                raise PrimeError(f"{self.name}: drives not operation-enabled within {self.enable_timeout_s:g} s: "
                                 + "; ".join(self._describe_drive(k) for k in np.flatnonzero(~self._enabled)))

    def latched_faults(self) -> list[str]:
        return [self._describe_drive(k) for k in np.flatnonzero(self._fault)]

    def reset_faults(self) -> None:
        """The operator's reset: every faulted drive gets one fault reset with the next write, and every drive
        held disabled after dropping out is enabled again, once its slave is back in OP."""
        self._reset_requested = True

    # ---------------------------------------------------------------------------- hot path
    def _gather(self) -> None:
        """Raw inputs into joint order, and which drives are enabled or faulted."""
        np.take(self._inputs, self.ring, out=self._rec)
        np.copyto(self._raw_pos, self._rec_pos)
        np.copyto(self._raw_vel, self._rec_vel)
        np.copyto(self._raw_tq, self._rec_tq)
        np.bitwise_and(self._rec_sw, _OPERATION_ENABLED_MASK, out=self._sw7)
        np.equal(self._sw7, _OPERATION_ENABLED, out=self._enabled)
        np.bitwise_and(self._rec_sw, _FAULT_MASK, out=self._sw7)
        np.equal(self._sw7, _FAULT, out=self._fault)

    def _step_controlwords(self, reset: np.ndarray | None = None) -> None:
        """Per drive, the controlword one step toward enabled; drives in ``reset`` that are in fault get a
        fault reset (as does every faulted drive once after ``reset_faults``). A fault reset is a rising edge,
        so it alternates."""
        np.bitwise_and(self._rec_sw, 0x7F, out=self._sw7)
        np.take(self._cw_table, self._sw7, out=self._cw)
        if reset is not None:
            np.copyto(self._cw, FAULT_RESET, where=reset & self._fault)
        if self._reset_requested:
            self._reset_requested = False
            np.copyto(self._cw, FAULT_RESET, where=self._fault)
            back = self.master.slave_ok[self.ring]
            self._held_off &= ~back  # a drive whose slave is still away stays held: it cannot be reset yet
        if self._held_off.any():
            np.copyto(self._cw, DISABLE_VOLTAGE, where=self._held_off)
        np.equal(self._cw, FAULT_RESET, out=self._scratch)
        np.equal(self._cw_prev, FAULT_RESET, out=self._mask)
        np.logical_and(self._scratch, self._mask, out=self._scratch)
        np.copyto(self._cw, DISABLE_VOLTAGE, where=self._scratch)
        np.copyto(self._cw_prev, self._cw)
        self._out_cw[self.ring] = self._cw

    def read(self, now: float, state: StateArrays) -> None:
        master = self.master
        began = time.perf_counter()
        wkc = master.receive()
        self.io_s = time.perf_counter() - began
        self._gather()
        dropped = self._dropped  # enabled in the last frame, now neither enabled nor in fault
        np.logical_or(self._enabled, self._fault, out=dropped)
        np.logical_not(dropped, out=dropped)
        np.logical_and(dropped, self._was_enabled, out=dropped)
        np.logical_or(self._held_off, dropped, out=self._held_off)
        np.copyto(self._was_enabled, self._enabled)  # scratch above, allocation-free: these run every tick
        x3 = self._x3
        np.multiply(self._raw, self.state_factor, out=x3)
        np.add(x3, self.state_offset, out=x3)
        state.data[:, self.indices] = x3
        if wkc != master.expected_wkc:
            self.wkc_errors += 1
            self._wkc_bad_cycles += 1
        else:
            self._wkc_bad_cycles = 0
        if (self._wkc_bad_cycles >= self.wkc_tolerance_cycles) != self._wkc_flagged:
            self._update_wkc_flag(wkc)
        if master.health_version != self._health_seen:
            self._update_health_flags()
        if self._fault_seen or np.count_nonzero(self._fault):
            self._update_fault_flags()
        if not np.array_equal(self._held_off, self._held_off_seen):
            self._update_held_flags()

    def write(self, now: float, command: CommandArrays) -> None:
        idx = self.indices
        x, t, follow, hold, scratch = self._x, self._t, self._follow, self._mask, self._scratch
        # position: the CSP target; NaN holds the last target; zero stiffness or a drive that is not
        # enabled follows the actual position
        np.take(command.position, idx, out=x)
        np.multiply(x, self.command_factor[0], out=t)
        np.add(t, self.command_offset[0], out=t)
        np.isfinite(t, out=hold)
        np.logical_not(hold, out=hold)
        np.copyto(t, self._held, where=hold)
        np.take(command.stiffness, idx, out=self._kp)
        np.equal(self._kp, 0.0, out=follow)
        np.logical_not(hold, out=scratch)
        np.logical_and(follow, scratch, out=follow)
        np.logical_not(self._enabled, out=scratch)
        np.logical_or(follow, scratch, out=follow)
        np.copyto(t, self._raw_pos, where=follow)
        _round_clamp(t, _TARGET_LIMITS, self._i32)
        self._out_target[self.ring] = self._i32
        np.copyto(self._held, self._i32)
        # velocity offset (the damping term's feed-forward) and torque offset (effort feed-forward), zero
        # where not finite or the drive is not enabled
        x2, bad2 = self._x2, self._mask2
        np.take(command.velocity, idx, out=self._x2_vel)
        np.take(command.effort, idx, out=self._x2_eff)
        np.multiply(x2, self._ff_factor, out=x2)
        np.add(x2, self._ff_offset, out=x2)
        np.isfinite(x2, out=bad2)
        np.logical_and(bad2, self._enabled, out=bad2)
        np.logical_not(bad2, out=bad2)
        np.copyto(x2, 0.0, where=bad2)
        _round_clamp(x2, _FF_LIMITS, self._i32_2)
        self._out_vel[self.ring] = self._ff_vel
        self._out_tq[self.ring] = self._ff_tq
        self._out_mode[:] = MODE_CSP
        self._step_controlwords()
        began = time.perf_counter()
        self.master.send()
        self.io_s += time.perf_counter() - began

    # ------------------------------------------------------------------------------- flags
    def _update_wkc_flag(self, wkc: int) -> None:
        master = self._master()
        self._wkc_flagged = not self._wkc_flagged
        if self._wkc_flagged:
            self.set_flag("ethercat/wkc", f"EtherCAT working counter {wkc}, expected {master.expected_wkc} on "
                                          f"{master.interface} for {self._wkc_bad_cycles} cycles: process data is "
                                          "not reaching every drive")
        else:
            self.clear_flag("ethercat/wkc")

    def _update_health_flags(self) -> None:
        master = self._master()
        self._health_seen = master.health_version
        lost = getattr(master, "lost", None)
        for k, joint in enumerate(self.joints):
            position = int(self.ring[k])
            key = f"ethercat/ring{position}/lost"
            if master.slave_ok[position]:
                self.clear_flag(key)
                continue
            state = int(master.al_state[position])
            why = "not answering" if lost is not None and lost[position] else f"in {describe_al_state(state)}"
            self.set_flag(key, f"{joint} (ring {position}): slave lost ({why}); recovering")

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
        for k in np.flatnonzero(self._held_off != self._held_off_seen):
            key = f"ethercat/ring{int(self.ring[k])}/disabled"
            if self._held_off[k]:
                self.set_flag(key, f"{self.joints[k]} (ring {int(self.ring[k])}): the drive dropped out of operation "
                                   "(power or link) and is held disabled, so it cannot snap to the target when it "
                                   "comes back (latched: r in the live table, or `prime reset`, once it is in OP)")
            else:
                self.clear_flag(key)
        np.copyto(self._held_off_seen, self._held_off)

    def _describe_drive(self, k: int) -> str:
        sw, err = int(self._rec_sw[k]), int(self._rec_err[k])
        text = (f"{self.joints[k]} (ring {int(self.ring[k])}): {drive_state(sw).value}, statusword {sw} "
                f"(0x{sw:04X}), error 0x{err:04X} {describe_error(err)}")
        hint = ERROR_HINTS.get(err)
        return f"{text}: {hint}" if hint else text


def _checked(config: SlaveConfig, channel: Channel, index: int) -> Channel:
    """A MIT channel must sit on the object this component reads or writes (the PDO layout is fixed)."""
    if channel.index != index:
        raise ConfigError(config.source, f"0x{channel.index:04X}",
                          f"the {channel.interface} channel maps object 0x{channel.index:04X}, expected 0x{index:04X}",
                          "regenerate the slave configs with `prime calibration fold`")
    return channel
