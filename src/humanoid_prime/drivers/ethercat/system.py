"""``EthercatSystem``: the ten eRob arm joints as one hardware component, CiA402 CSP over an EtherCAT master.

Calibration is applied exactly as the C++ stack applies it: at configure time the calibration is folded
into one per-slave config per joint (``fold.py``, in memory), each is validated with
``parse_slave_config``, and every channel converts with ``value = factor * x + offset`` (DESIGN §2).

Per tick, ``read`` collects the frame and converts position, velocity and effort into the joint frame;
``write`` converts the command into CSP targets and sends the frame. While a joint's commanded stiffness
is zero, or its drive is not operation-enabled, its CSP target follows the actual position, so a limp arm
never accumulates following error (0x8500) and enabling never jumps. A NaN position means no command:
the drive keeps its last target and holds there with its own gains (e.g. the joints nobody sweeps during
calibration). Both are one compiled call each (``_tick.pyx``) on arrays preallocated here, and the
process image is reached through views bound once.

Safety flags (worded in ``system_flags.py``): ``ethercat/wkc`` (working counter mismatch for
``wkc_tolerance_cycles`` cycles in a row), ``ethercat/ring<N>/lost`` (slave not in OP or not answering),
``ethercat/ring<N>/fault`` (drive fault: decoded statusword and error code), and the warning
``ethercat/ring<N>/rated_torque`` (the drive's 0x6076 could not be read at bring-up, so its efforts use the nominal
rated torque).

Efforts are per mille of each drive's rated torque, read from 0x6076 in PRE-OP: the fold's factors assume
the nominal figure (the C++ stack cannot read it), and are rescaled here once the drive has said its own.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from humanoid_prime.config.calibration import Calibration
from humanoid_prime.config.description import ETHERCAT_BLOCK
from humanoid_prime.config.robot import Robot
from humanoid_prime.control.flags import Level
from humanoid_prime.control.hardware import DriveStatus
from humanoid_prime.control.interfaces import CommandArrays, StateArrays
from humanoid_prime.control.rate import Rate
from humanoid_prime.drivers.erob.cia402 import (
    BRINGUP_TRANSIENT_FAULT,
    DISABLE_VOLTAGE,
    FAULT_PATTERN,
    FAULT_RESET,
    OPERATION_ENABLED_PATTERN,
    enable_step,
)
from humanoid_prime.drivers.erob.constants import MODE_CSP, RATED_TORQUE_NM
from humanoid_prime.drivers.erob.drive_state import Drive, Event, after, apply_event, frame_table
from humanoid_prime.drivers.erob.objects import (
    POSITION_ACTUAL,
    TARGET_POSITION,
    TORQUE_ACTUAL,
    TORQUE_OFFSET,
    TORQUE_OFFSET_LIMIT_PER_MILLE,
    VELOCITY_ACTUAL,
    VELOCITY_OFFSET,
)
from humanoid_prime.drivers.ethercat._tick import EcTick
from humanoid_prime.drivers.ethercat.fold import check_foldable, fold_slave_config, write_folded_configs
from humanoid_prime.drivers.ethercat.master import RX_DTYPE, TX_DTYPE, BringupReport, EthercatMaster
from humanoid_prime.drivers.ethercat.priority import feeding_priority
from humanoid_prime.drivers.ethercat.ring import ExpectedSlave, check_ring
from humanoid_prime.drivers.ethercat.slave_config import Channel, SlaveConfig, parse_slave_config
from humanoid_prime.drivers.ethercat.system_flags import EthercatFlags
from humanoid_prime.errors import ConfigError, PrimeError


def _pdo_limits(field: str) -> tuple[float, float]:
    """(min, max) of the mapped integer type of ``field``."""
    limits = np.iinfo(RX_DTYPE[field])
    return float(limits.min), float(limits.max)


FAULT_RESET_GRACE_S = 0.5  # a drive out of its fault within this long of our fault reset left it by that reset
_TARGET_LIMITS = _pdo_limits("target_position")
_VELOCITY_OFFSET_LIMITS = _pdo_limits("velocity_offset")
# 0x60B2 accepts +-3000 per mille of the rated torque (ZeroErr EDS V1.5), narrower than its INTEGER16
_TORQUE_OFFSET_LIMITS = (-float(TORQUE_OFFSET_LIMIT_PER_MILLE), float(TORQUE_OFFSET_LIMIT_PER_MILLE))
_MIT = ("position", "velocity", "effort")
_STATE_OBJECTS = (POSITION_ACTUAL, VELOCITY_ACTUAL, TORQUE_ACTUAL)
_COMMAND_OBJECTS = (TARGET_POSITION, VELOCITY_OFFSET, TORQUE_OFFSET)


def _controlword_table(auto_fault_reset: bool) -> npt.NDArray[np.uint16]:
    """Controlword for every value of ``statusword & 0x7F`` (the bits the CiA402 state depends on)."""
    table = np.array([enable_step(sw) for sw in range(0x80)], dtype=np.uint16)
    if not auto_fault_reset:
        table[table == FAULT_RESET] = DISABLE_VOLTAGE
    return table


class EthercatSystem(EthercatFlags):
    """The eRob joints of ``robot`` (canonical order), each bound to its ring position."""

    def __init__(self, robot: Robot, calibration: Calibration, *, update_rate: float,
                 bringup_rate: float = 1000.0, master: EthercatMaster | None = None,
                 interface: str | None = None, config_dir: str | Path | None = None,
                 enable_timeout_s: float = 5.0, wkc_tolerance_cycles: int = 3,
                 name: str = ETHERCAT_BLOCK, emulated: bool = False) -> None:
        hw = robot.hardware
        self.emulated = emulated  # the emulated ring: a silence is the emulator's, there is no cable
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
        self.on_restore_needed: Callable[[], None] | None = None
        self._allocate(len(self.joints))

    def _allocate(self, n: int) -> None:
        """The per-joint arrays, joint order, preallocated for the tick (the compiled kernel is bound to them)."""
        # factor/offset per MIT interface (rows position, velocity, effort)
        self.state_factor, self.state_offset = np.ones((3, n)), np.zeros((3, n))
        self.command_factor, self.command_offset = np.ones((3, n)), np.zeros((3, n))
        # the rated torque each drive reported (0x6076), NaN where it could not be read and the fold's
        # nominal figure scales the efforts instead
        self.rated_torque_nm = np.full(n, math.nan)
        self._fold_effort = (np.ones(n), np.ones(n))  # the fold's effort factors (state, command), nominal torque
        self._cw_table = _controlword_table(False)  # a fault latches (see _enable for the one exception)
        self._reset_requested = False
        self._rec = np.zeros(n, TX_DTYPE)  # the inputs of this component's slaves
        self._rec_sw, self._rec_err = self._rec["statusword"], self._rec["error_code"]
        self._raw = np.zeros((3, n))  # position, velocity, effort as raw counts / per mille
        self._cw_prev = np.zeros(n, np.uint16)  # the controlword last sent
        self._enabled = np.zeros(n, dtype=bool)  # in the last frame read
        self._fault = np.zeros(n, dtype=bool)
        # Each drive's state (drivers/erob/drive_state.py), moved by every frame and by the operator's reset. A drive
        # that drops out (its slave lost power or link and came back) is held disabled until the operator's reset:
        # enabling it on its own would drive the joint, which hung limp meanwhile, straight to the mode's target.
        # With ``on_restore_needed`` (the impedance manager restores what a power loss clears, and is woken by it)
        # a held drive is RESTORING until ``settings_restored`` for its slave, and no reset releases it before.
        self._state = np.full(n, Drive.ENABLING, dtype=np.uint8)
        self._grace = np.zeros(n, np.uint16)  # frames left in which a fault reset of ours may take effect
        self._held_seen = np.zeros(n, dtype=bool)  # held, when the flags were last worded
        self._restored: collections.deque[tuple[int, int]] = collections.deque()  # (joint, left OP count) told
        self._came_back: list[str] = []  # lost flags of slaves that were back in OP when the loop looked
        self._left_op_seen = np.zeros(n, dtype=np.int64)  # each slave's departures from OP, when the loop last looked
        self._held = np.zeros(n)  # the last CSP target sent (raw), what a NaN position command keeps
        self._tick: EcTick | None = None  # the compiled read and write, bound to the process image at start
        self._wkc_flagged = False
        self._wkc_silent = False  # the flag says that nothing answered (working counter <= 0)
        self._fault_seen: tuple[tuple[np.intp, int, int], ...] = ()  # (joint k, statusword, error code)
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
            self._scale_efforts()
        self._bind_views()
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
    def enabled(self) -> npt.NDArray[np.bool_]:
        """Per joint: its drive reported operation enabled in the last frame read (copy)."""
        return self._enabled.copy()

    @property
    def faulted(self) -> npt.NDArray[np.bool_]:
        """Per joint: its drive reported fault in the last frame read (copy)."""
        return self._fault.copy()

    @property
    def bus_ready(self) -> bool:
        """True once every slave is in OP and joint states flow: SDOs (gains) may go out."""
        return self.master is not None and self.master.sdo_ready

    def _bound_tick(self) -> EcTick:
        if self._tick is None:
            raise PrimeError(f"{self.name}: not started")
        return self._tick

    def _bind_views(self) -> None:
        master = self._master()
        inputs, outputs = master.inputs, master.outputs
        self._in_pos = inputs["position_actual"]
        self._out_cw = outputs["controlword"]
        self._out_target = outputs["target_position"]
        self._out_vel = outputs["velocity_offset"]
        self._out_tq = outputs["torque_offset"]
        self._out_mode = outputs["mode_of_operation"]
        self._tick = EcTick(inputs, outputs, self._rec, self.ring, self.indices, self._raw, self.state_factor,
                            self.state_offset, self.command_factor, self.command_offset, self._held,
                            self._enabled.view(np.uint8), self._fault.view(np.uint8), self._state, frame_table(),
                            (Drive.FAULT, Drive.RESETTING, Drive.HELD), self._cw_table, self._cw_prev,
                            OPERATION_ENABLED_PATTERN, FAULT_PATTERN, FAULT_RESET, DISABLE_VOLTAGE, MODE_CSP,
                            _TARGET_LIMITS, _VELOCITY_OFFSET_LIMITS, _TORQUE_OFFSET_LIMITS, self._grace)
        self._tick.grace_ticks = max(3, round(FAULT_RESET_GRACE_S * self.update_rate))

    def _enable(self) -> None:
        """CiA402 enable at the bring-up rate: target on the actual position first, then step to enabled.

        A fault latches (it waits for the operator's reset), with one exception: the EtherCAT communication
        fault (0xA000) a drive may raise while DC locks during bring-up is reset here, so it clears by itself.
        Enabling ends when every drive is enabled or latched in another fault (flagged by ``read``)."""
        with feeding_priority():
            self._enable_drives()

    def _enable_drives(self) -> None:
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
                self._held[:] = self._out_target[self.ring]  # a NaN command holds the position enabled at
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

    def drive_states(self) -> list[DriveStatus]:
        master = self.master
        if master is None or len(master.al_state) == 0:
            return []
        statuswords, errors, al_states = self._rec_sw.tolist(), self._rec_err.tolist(), master.al_state.tolist()
        return [DriveStatus(joint, statuswords[k], errors[k], al_states[position])
                for k, (joint, position) in enumerate(zip(self.joints, self.ring.tolist(), strict=True))]

    def reset_faults(self) -> None:
        """The operator's reset: every faulted drive gets one fault reset with the next write, and every drive
        held disabled after dropping out is enabled again, once its slave is back in OP."""
        self._reset_requested = True

    # ---------------------------------------------------------------------------- hot path
    def _gather(self) -> None:
        """Raw inputs into joint order, and which drives are enabled or faulted."""
        self._bound_tick().gather()

    def _take_reset(self) -> npt.NDArray[np.uint8] | None:
        """The drives the operator's reset, if one was asked for since the last controlwords, resets (those in
        fault; None: no reset). It also releases the held drives whose slave is back in OP (a RESTORING one is
        not released: its settings are not back yet)."""
        if not self._reset_requested:
            return None
        self._reset_requested = False
        self._apply_restored()
        if apply_event(self._state, Event.RESET, where=self._master().slave_ok[self.ring]).any():
            self._update_held_flags()
        return self._fault.view(np.uint8)

    def awaiting_restore(self) -> list[tuple[int, int]]:
        """Held drives whose slave is back in OP and whose settings wait to be restored: (ring position, how often
        the slave has left OP so far, to hand back to ``settings_restored``)."""
        master = self._master()
        waiting = np.flatnonzero((self._state == Drive.RESTORING) & master.slave_ok[self.ring])
        return [(int(self.ring[k]), int(master.left_op[self.ring[k]])) for k in waiting]

    def restore_pending(self) -> list[int]:
        """Ring positions of held drives whose settings are not restored yet (their slave in OP or not)."""
        return [int(self.ring[k]) for k in np.flatnonzero(self._state == Drive.RESTORING)]

    def settings_restored(self, position: int, left_op: int) -> None:
        """The settings of the drive at ring ``position`` are back (called from the restoring thread): the
        operator's reset may release it once the loop's thread has taken this in. Not if its slave left OP again
        since ``awaiting_restore`` said ``left_op``: it may have lost them again, and waits for another restore."""
        k = int(np.flatnonzero(self.ring == position)[0])
        self._restored.append((k, left_op))

    def _apply_restored(self) -> bool:
        """In the loop's thread (the only one that moves the drives' states): the restores reported meanwhile."""
        applied = False
        master = self._master()
        while self._restored:
            k, left_op = self._restored.popleft()
            position = int(self.ring[k])
            if master.left_op[position] == left_op and master.slave_ok[position]:
                self._state[k] = after(Drive(self._state[k]), Event.RESTORED)
                applied = True
        return applied

    def _step_controlwords(self, reset: npt.NDArray[np.uint8] | None = None) -> None:
        """Per drive, the controlword one step toward enabled; drives in ``reset`` that are in fault get a
        fault reset (as does every faulted drive once after ``reset_faults``). A fault reset is a rising edge,
        so it alternates."""
        operator = self._take_reset()
        if reset is not None and operator is not None:
            reset = reset | operator.view(bool)
        elif operator is not None:
            reset = operator.view(bool)
        self._bound_tick().controlwords(None if reset is None else reset.view(np.uint8))

    def read(self, now: float, state: StateArrays) -> None:
        master, tick = self.master, self._tick
        assert master is not None and tick is not None  # bound when the component started
        began = time.perf_counter()
        wkc = master.receive()
        self.io_s = time.perf_counter() - began
        # also holds disabled every drive that was enabled in the last frame and is now neither enabled nor in
        # fault: it dropped out (power or link)
        faulted, held_changed = tick.read(state.data)
        if wkc != master.expected_wkc:
            self.wkc_errors += 1
            self._wkc_bad_cycles += 1
        else:
            self._wkc_bad_cycles = 0
        if (self._wkc_bad_cycles >= self.wkc_tolerance_cycles) != self._wkc_flagged or (
                self._wkc_flagged and (wkc <= 0) != self._wkc_silent):
            self._update_wkc_flag(wkc)
        while self._came_back:  # said for one tick (_update_health_flags says it again if it left OP again)
            self.clear_flag(self._came_back.pop())
        if master.health_version != self._health_seen:
            self._update_health_flags()
        if self._fault_seen or faulted:
            self._update_fault_flags()
        if self._restored and self._apply_restored():
            held_changed = True
        if held_changed:
            self._update_held_flags()

    def write(self, now: float, command: CommandArrays) -> None:
        """Position is the CSP target: NaN holds the last target, and zero stiffness or a drive that is not
        enabled follows the actual position. The velocity and torque offsets carry the damping term's and the
        effort's feed-forward, zero where not finite or where the drive is not enabled."""
        master, tick = self.master, self._tick
        assert master is not None and tick is not None  # as in read
        tick.write(command.data, self._take_reset())
        began = time.perf_counter()
        master.send()
        self.io_s += time.perf_counter() - began


def _checked(config: SlaveConfig, channel: Channel, index: int) -> Channel:
    """A MIT channel must sit on the object this component reads or writes (the PDO layout is fixed)."""
    if channel.index != index:
        raise ConfigError(config.source, f"0x{channel.index:04X}",
                          f"the {channel.interface} channel maps object 0x{channel.index:04X}, expected 0x{index:04X}",
                          "regenerate the slave configs with `prime calibration fold`")
    return channel
