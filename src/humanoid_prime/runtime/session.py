"""The composition root of a run on the robot: configuration, hardware components, controller manager and
impedance manager, put together in the order DESIGN §3 makes impossible to get wrong.

1. ``plan_session`` loads and cross-checks the configuration; the SYNC0 cycle is derived from
   ``update_rate`` (an explicit ``sync0_period`` that differs is refused with the reason) before anything
   touches a bus;
2. ``open_session`` builds one hardware component per hardware block of the chosen backends (by the
   description's block names, through ``assemble``, which puts every run together: the simulation, hardware
   in the loop and the benchmarks too) and starts the controller manager: the eRob ring reaches OP with the fast
   bring-up loop and the drives are enabled, the Sito wrists are activated (gains, then enable), and the
   controllers start in stages (joint-state broadcaster, ZERO_TORQUE active, the other modes inactive; or
   the broadcaster alone for a single-bus run);
3. only then, with every slave in OP and joint states flowing, the impedance manager arms the gain gate
   and follows ``/control_mode``.

Everything opened is registered on the caller's ExitStack; ``runtime.run`` runs the loop and tears down;
``runtime.report`` is what the run says of itself.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, cast

from humanoid_prime.calibration.journal import OverrideJournal
from humanoid_prime.calibration.limp import restore_left
from humanoid_prime.config.calibration import Calibration, load_calibration
from humanoid_prime.config.controllers import ControllersConfig, check_command_limits, load_controllers
from humanoid_prime.config.description import BACKEND_BLOCKS, ETHERCAT_BLOCK, SITO_BLOCK
from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.control.flags import Level
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import SAFETY_STATUS, SafetyStatus
from humanoid_prime.drivers.erob.constants import MIN_CYCLE_S
from humanoid_prime.drivers.erob.gains import check_erob_limits, check_mode_gains
from humanoid_prime.drivers.erob.objects import BUS_GAIN_GATE
from humanoid_prime.drivers.ethercat.fold import check_foldable
from humanoid_prime.drivers.ethercat.master import sync0_period_ns
from humanoid_prime.drivers.ethercat.sdo_client import SizedSdo
from humanoid_prime.drivers.sito.system import check_wire_limits
from humanoid_prime.errors import ConfigError, PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.impedance import ImpedanceManager
from humanoid_prime.runtime.readout import state_source
from humanoid_prime.runtime.realtime import lock_memory, tighten_switch_interval
from humanoid_prime.runtime.registry import ComponentSettings, build_components
from humanoid_prime.runtime.report import FaultRecord, RunEnd, read_end, run_problems, run_summary
from humanoid_prime.runtime.socket import ControlServer
from humanoid_prime.runtime.switching import mode_switcher

if TYPE_CHECKING:
    from humanoid_prime.drivers.ethercat.system import EthercatSystem
    from humanoid_prime.drivers.sito.system import SitoSystem

BACKENDS = tuple(BACKEND_BLOCKS)
BUS_READY_S = 5.0  # the longest a run waits for its ring to carry SDOs (as the impedance manager does)
MOVING_MODES = (Mode.STANDBY, Mode.LOCOMOTION, Mode.REMOTE)  # modes whose commands drive joints to targets


@dataclass
class BringupOptions:
    backends: str = "all"
    emulated: bool = False  # the buses lead to the virtual Prime (reported in the summary)
    hardware_file: str | Path | None = None
    calibration_file: str | Path | None = None
    calibration: Calibration | None = None  # overrides calibration_file (calibration runs use identity)
    broadcaster_only: bool | None = None  # default: single-bus runs only
    controllers_file: str | Path | None = None
    interface: str | None = None  # EtherCAT NIC (default: prime_hardware.yaml)
    ec_mailbox: str | None = None  # who works the eRob's mailboxes, prime or soem (default: prime_hardware.yaml)
    can_interface: str | None = None  # python-can interface (default: prime_hardware.yaml)
    can_channel: str | None = None
    sync0_period_s: float | None = None  # must equal 1/update_rate; only for an explicit cross-check
    bringup_rate: float | None = None  # Hz of the EtherCAT bring-up loop (default: prime_controllers.yaml)
    parallel_sdo: bool | None = None  # default: prime_controllers.yaml
    duration: float | None = None  # seconds of control loop after bringup; None = until stopped
    mode: Mode | None = None  # switch to this mode once up, and keep running
    sequence: Sequence[Mode] = ()  # modes to visit, one every ``dwell`` seconds, then stop
    dwell: float = 2.0
    erob_config_dir: str | Path | None = None  # also write the folded per-slave configs here
    control_socket: str | Path | None = None
    update_rate: float | None = None  # Hz of the control loop (default: prime_controllers.yaml)
    realtime: bool = False  # the loop thread takes real-time scheduling, locked memory, a frozen GC
    cpu: int | None = None  # (with realtime) pin the loop thread to this CPU
    uncalibrated: bool = False  # on the robot, allow the modes that move joints with an identity calibration
    config: dict[str, dict[str, object]] | None = None  # the files used (path, sha256, source), for the reports
    # the robot's state folder: a drive a killed `prime limp` left limp there is restored once the ring is up
    state_folder: Path | None = None


@dataclass
class Plan:
    """Everything decided before a bus is touched: the checked configuration and the rates."""

    options: BringupOptions
    robot: Robot
    config: ControllersConfig
    calibration: Calibration
    update_rate: float
    bringup_rate: float
    parallel_sdo: bool
    broadcaster_only: bool
    began: float
    stages: list[tuple[str, float]] = field(default_factory=list)
    control: ControlServer | None = None  # the run's control socket, claimed before any bus
    memory_refused: str | None = None  # (with options.realtime) why memory could not be locked; None: locked
    refused: str | None = None  # why the modes that move joints are refused in this run (None: they are not)
    on_stage: Callable[[str], None] | None = None  # told each bring-up stage as it completes (a live status)

    def stage(self, name: str, since: float) -> float:
        """Record a bring-up stage that started at ``since``; returns now."""
        now = time.monotonic()
        self.stages.append((name, now - since))
        if self.on_stage is not None:
            self.on_stage(name)
        return now


def claim_control_socket(plan: Plan, stack: contextlib.ExitStack) -> ControlServer:
    """Bind the run's control socket before anything touches a bus: a second instance stops here, with the
    reason, instead of after it has opened the NIC. ``open_session`` attaches the running session to it."""
    plan.control = stack.enter_context(ControlServer(path=plan.options.control_socket))
    return plan.control


def check_robot_config(robot: Robot, config: ControllersConfig, calibration: Calibration) -> None:
    """What only the drive facts can check, before anything opens, each naming the file and key: every mode's
    eRob gains realisable, the loop rate within the eRob's minimum cycle, the calibration foldable."""
    check_mode_gains(config, robot.hardware)
    check_command_limits(config, robot)
    check_erob_limits(robot.hardware)
    check_wire_limits(robot, calibration=calibration)
    try:
        sync0_period_ns(config.update_rate)
    except PrimeError as exc:
        raise ConfigError(config.path, "controller_manager.ros__parameters.update_rate", str(exc)) from None
    check_foldable(robot, calibration)


def default_bringup_rate(configured: float, update_rate: float) -> float:
    """The bring-up loop runs at least twice as fast as SYNC0 (up to the eRob's 2 kHz), so a late frame
    still leaves every SYNC0 cycle a fresh one while the drives lock onto the distributed clock."""
    return max(configured, min(2.0 * update_rate, 1.0 / MIN_CYCLE_S))


def plan_session(options: BringupOptions) -> Plan:
    """Load and cross-check the configuration for ``options``; nothing is opened."""
    if options.backends not in BACKEND_BLOCKS:
        raise PrimeError(f"backends must be one of {', '.join(BACKENDS)}, got {options.backends!r}")
    began = time.monotonic()
    robot = load_robot(options.hardware_file)
    config = load_controllers(robot.names, options.controllers_file)
    calibration = options.calibration or load_calibration(robot.hardware, options.calibration_file)
    check_robot_config(robot, config, calibration)
    update_rate = config.update_rate if options.update_rate is None else options.update_rate
    if options.update_rate is not None:
        sync0_period_ns(update_rate)  # the eRob's minimum cycle bounds --rate as it bounds the file's rate
    sync0_period_ns(update_rate, sync0_period_s=options.sync0_period_s)  # refuse a mismatch before the bus
    broadcaster_only = options.backends != "all" if options.broadcaster_only is None else options.broadcaster_only
    plan = Plan(options, robot, config, calibration, update_rate=update_rate,
                bringup_rate=options.bringup_rate or default_bringup_rate(config.bringup_rate, update_rate),
                parallel_sdo=config.impedance.parallel_sdo if options.parallel_sdo is None else options.parallel_sdo,
                broadcaster_only=broadcaster_only, began=began, refused=uncalibrated_refusal(options, calibration))
    asked = [mode for mode in (options.mode, *options.sequence) if mode in MOVING_MODES]
    if plan.refused is not None and asked and not broadcaster_only:
        raise PrimeError(f"{asked[0].value} refused: {plan.refused}")
    plan.stage("configuration", began)
    return plan


def uncalibrated_refusal(options: BringupOptions, calibration: Calibration) -> str | None:
    """Why a run on the real robot may not enter a mode that moves a joint: its calibration is the identity
    template, so STANDBY's pose would drive each arm to where wrong offsets put it. None: no reason."""
    if options.emulated or options.uncalibrated or not calibration.is_identity:
        return None
    where = f" ({calibration.path})" if calibration.path is not None else ""
    return (f"the calibration{where} is the identity template (every homing_offset 0), so a target pose would "
            "drive the arms somewhere nobody expects; calibrate this robot (prime calibrate), or pass "
            "--uncalibrated if the offsets really are 0")


@dataclass
class Session:
    """Everything a running bringup holds; ``summary()`` is the report of the run."""

    plan: Plan
    manager: ControllerManager
    ethercat: EthercatSystem | None = None
    sito: SitoSystem | None = None
    impedance: ImpedanceManager | None = None
    bringup_seconds: float = 0.0
    faults: list[FaultRecord] = field(default_factory=list)
    gate_reset_failures: list[str] = field(default_factory=list)
    end: RunEnd = field(default_factory=lambda: RunEnd())  # what held when the run ended (capture_end)
    reports: dict[str, object] = field(default_factory=dict)  # further sections of the summary (e.g. load_test)
    final_position: dict[str, float | None] = field(default_factory=dict)  # keep_final_position
    _open: dict[str, FaultRecord] = field(default_factory=dict)

    @property
    def robot(self) -> Robot:
        return self.plan.robot

    @property
    def config(self) -> ControllersConfig:
        return self.plan.config

    @property
    def options(self) -> BringupOptions:
        return self.plan.options

    @property
    def stages(self) -> list[tuple[str, float]]:
        return self.plan.stages

    def mark_limp(self, joint: str, limp: bool) -> None:
        """In a broadcaster-only run, from the next tick: while ``limp``, ``joint``'s target follows where it is at
        zero stiffness, so its CSP target follows the actual position (no following error while it is swept);
        otherwise no command again, and the drive holds where it is. The passive controller writes it, through
        the gate, as every command."""
        passive = self.manager.passive
        if passive is None:
            raise PrimeError("a joint is marked limp only in a broadcaster-only run (a calibration or single-bus run)")
        passive.mark_limp(self.robot.index(joint), limp)

    def note(self, status: SafetyStatus) -> None:
        """Keep the history of every flag: opened when it appears, closed when it clears, at the time the loop
        publishes the change. Not at the status's stamp, the start of its tick: the tick reads the ring and applies
        the requests after it, so a reset sent meanwhile by another thread would look later than the flag it
        cleared."""
        now = time.monotonic() - self.plan.began
        for key, text in status.flags.items():
            if key not in self._open:
                record = FaultRecord(key, text, status.levels.get(key, Level.ERROR), now)
                self._open[key] = record
                self.faults.append(record)
        for key in [key for key in self._open if key not in status.flags]:
            self._open.pop(key).until_s = now

    def keep_final_position(self) -> None:
        """The joint angles of the control loop's last tick (rad, joint frame; None: unknown), kept for the
        summary before the teardown moves anything."""
        self.final_position = {name: (float(q) if math.isfinite(q) else None)
                               for name, q in zip(self.robot.names, self.manager.resources.state.position,
                                                  strict=True)}

    def record_fault(self, key: str, text: str, level: Level = Level.ERROR) -> None:
        """A problem that is no flag of a component (a tool of the run failed, a teardown step did not take)."""
        self.faults.append(FaultRecord(key, text, level, time.monotonic() - self.plan.began, None))

    def capture_end(self) -> None:
        """What holds as the run ends, read fresh from the buses before they close: slaves in OP, drives
        enabled or faulted, wrists heard from."""
        self.end = read_end(self)

    @property
    def problems(self) -> list[str]:
        """Why this run is not a success, one line each (empty: every device did what it was asked)."""
        return run_problems(self)

    def summary(self) -> dict[str, object]:
        return run_summary(self)


def assemble(settings: ComponentSettings, config: ControllersConfig, parts: Sequence[str | HardwareComponent], *,
             broadcaster_only: bool = False, clock: Callable[[], float] = time.monotonic) -> ControllerManager:
    """Put a run together: one hardware component per part, in order (a block name of the robot description is
    built by the registry; a component the caller built itself, such as the wrists of a hardware-in-the-loop
    run on an emulated bus, is taken as it is), under one controller manager at ``settings.update_rate``,
    not started."""
    components = [build_components((part,), settings)[0] if isinstance(part, str) else part for part in parts]
    return ControllerManager(settings.robot, components, config, update_rate=settings.update_rate,
                             broadcaster_only=broadcaster_only, clock=clock)


def open_session(plan: Plan, stack: contextlib.ExitStack) -> Session:
    """Bring Prime up as ``plan`` says; everything opened is registered on ``stack`` for teardown."""
    options, robot = plan.options, plan.robot
    if options.realtime:
        plan.memory_refused = lock_memory()
    stack.callback(sys.setswitchinterval, tighten_switch_interval(1.0 / plan.update_rate))
    settings = ComponentSettings(
        robot, plan.calibration, update_rate=plan.update_rate, bringup_rate=plan.bringup_rate,
        ethercat_interface=options.interface, ethercat_mailbox=options.ec_mailbox,
        sync0_period_s=options.sync0_period_s, parallel_sdo=plan.parallel_sdo,
        erob_config_dir=options.erob_config_dir, can_interface=options.can_interface,
        can_channel=options.can_channel, emulated=options.emulated)
    manager = assemble(settings, plan.config, BACKEND_BLOCKS[options.backends],
                       broadcaster_only=plan.broadcaster_only)
    by_block = {component.name: component for component in manager.resources.components}
    stack.callback(manager.shutdown)
    manager.configuration = dict(options.config or {})
    if plan.refused is not None:
        manager.refuse_modes(MOVING_MODES, plan.refused)
    # each block's component is the class the registry builds for it
    session = Session(plan, manager, ethercat=cast("EthercatSystem | None", by_block.get(ETHERCAT_BLOCK)),
                      sito=cast("SitoSystem | None", by_block.get(SITO_BLOCK)))
    stack.callback(session.capture_end)  # before the buses close, after everything entered later
    manager.topics.subscribe(SAFETY_STATUS, session.note, latched=True)
    manager.start()
    plan.stages.extend(manager.stages)
    t = time.monotonic()
    manager.tick()  # the first read -> update -> write: joint states flow from here on
    t = plan.stage("first tick", t)
    session.bringup_seconds = t - plan.began

    ethercat = session.ethercat
    if ethercat is not None and options.state_folder is not None and not options.emulated:
        _restore_left_overrides(session, options.state_folder)  # before anything arms a gate
    if ethercat is not None and not plan.broadcaster_only:
        master = ethercat.master
        assert master is not None  # opened when the manager started
        impedance = ImpedanceManager(robot, master, plan.config.mode_gains(), parallel=plan.parallel_sdo,
                                     retries=plan.config.impedance.sdo_retries)
        session.impedance = impedance
        manager.add_flag_source(impedance)
        # Normally closed by run_loop while the loop still ticks; this covers an exception on the way.
        stack.callback(lambda: session.gate_reset_failures.extend(impedance.close()))
        # The bus is ready and joint states have flowed (the first tick); the worker arms the gate (while the
        # loop already ticks) and follows the mode.
        impedance.start(manager.topics, lambda: ethercat.bus_ready, timeout=BUS_READY_S,
                        why_not_ready=master.readiness, dropped=ethercat)
        plan.stage("impedance manager started", t)
    if plan.control is not None:
        serve(session, plan.control)
        stack.callback(plan.control.detach)  # answering stops, and limp joints are reset, before teardown
    return session


def _restore_left_overrides(session: Session, folder: Path) -> None:
    """Drives an override left as it made them (``calibration.journal``: a `prime limp` or a hands-free calibration
    killed outright) on this robot's ring, through this run's control socket, an IgH master or the run's own master,
    are restored from their records before
    anything else writes a drive, and each is said on stderr and among the run's faults. An emulated ring is new
    and is never restored from records (the robot's records stay for the robot)."""
    control = session.plan.control
    ways = ["igh", "master", *([f"socket {control.path.absolute()}"] if control is not None else [])]
    journals = [journal for journal in (OverrideJournal(folder, way) for way in ways) if journal.left()]
    ethercat = session.ethercat
    if not journals or ethercat is None:
        return
    deadline = time.monotonic() + BUS_READY_S
    while not ethercat.bus_ready:  # mailbox traffic before every slave is in OP faults a drive
        if time.monotonic() > deadline:
            raise PrimeError(f"drives left limp by a killed `prime limp` wait to be restored, and the ring did not "
                             f"come up within {BUS_READY_S:g} s to restore them")
        time.sleep(0.005)
    assert ethercat.master is not None  # opened when the manager started
    for journal in journals:
        for position, line in restore_left(ethercat.master, journal):
            print(line, file=sys.stderr, flush=True)
            session.record_fault(f"limp/ring{position}", line, Level.WARN)


def serve(session: Session, server: ControlServer) -> None:
    """Answer on ``server`` for ``session``: mode requests (full runs), the operator's fault reset, SDO through
    this process's EtherCAT master, and in broadcaster-only runs the limp marker of ``prime limp``."""
    manager = session.manager
    switch = None if manager.broadcaster_only else mode_switcher(manager, session.impedance)
    sdo = session.ethercat.master if session.ethercat is not None else None
    joint_limp = on_close = None
    if manager.broadcaster_only and sdo is not None:
        ring_joints = {pos: joint for joint, pos in session.robot.hardware.erob_slaves.items()}
        marked: set[int] = set()

        def joint_limp(position: int, limp: bool) -> str:
            joint = ring_joints.get(position)
            if joint is None:
                raise PrimeError(f"ring position {position} is not an eRob joint")
            session.mark_limp(joint, limp)
            (marked.add if limp else marked.discard)(position)
            return joint

        def on_close() -> None:
            """A `prime limp` still running elsewhere cannot restore once this run ends: put its drive back on
            factory gains (gate 0) rather than leave it limp in drive memory for the next bringup."""
            for position in sorted(marked):
                with contextlib.suppress(Exception):
                    SizedSdo(sdo).write(position, BUS_GAIN_GATE, 0)
                session.record_fault(f"limp/ring{position}", f"{ring_joints[position]} (ring {position}) was still "
                                     "limp when the run ended; its gate was reset to 0", Level.WARN)

    state, _ = state_source(manager)  # for the run's whole life
    server.attach(switch_mode=switch, sdo=sdo, joint_limp=joint_limp, on_close=on_close,
                  reset=manager.request_reset, state=state)
