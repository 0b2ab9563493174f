"""Whole-robot bringup: one controller manager over both buses, eRob impedance that follows the mode.

The order is the one DESIGN §3 makes impossible to get wrong:

1. load and cross-check the configuration; the SYNC0 cycle is derived from ``update_rate`` (an explicit
   ``sync0_period`` that differs is refused with the reason before anything touches the bus);
2. fold ``prime_calibration.yaml`` into the per-slave eRob configs, bring the ring to OP with the fast
   bring-up loop (``bringup_rate``, independent of the control rate) and enable the drives;
3. activate the Sito wrists (gains, then enable);
4. the staged controller start: joint-state broadcaster, ZERO_TORQUE active, the other modes loaded
   inactive — or, for a single-bus run, the broadcaster alone;
5. only then, with every slave in OP and joint states flowing, the impedance manager arms the gain gate
   and follows ``/control_mode``;
6. the control-rate loop runs until the duration ends, ``q``, Ctrl-C or SIGTERM; on the way out the gate
   is reset to 0 on every reachable slave before the drives are disabled and the wrists switched off.
"""

from __future__ import annotations

import contextlib
import signal
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from humanoid_prime.config.calibration import Calibration, load_calibration
from humanoid_prime.config.controllers import ControllersConfig, load_controllers
from humanoid_prime.config.robot import Robot, load_robot
from humanoid_prime.control.hardware import HardwareComponent
from humanoid_prime.control.manager import ControllerManager
from humanoid_prime.control.topics import SAFETY_STATUS, SafetyStatus
from humanoid_prime.drivers.erob.objects import BUS_GAIN_GATE, BUS_GAIN_GATE_FORMAT, POS_LOOP_GAIN, VEL_LOOP_GAIN
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode
from humanoid_prime.runtime.socket import ControlServer

BACKENDS = ("all", "ec", "can")


@dataclass
class BringupOptions:
    backends: str = "all"
    emulate: bool = False
    hardware_file: str | Path | None = None
    calibration_file: str | Path | None = None
    calibration: Calibration | None = None  # overrides calibration_file (calibration runs use identity)
    broadcaster_only: bool | None = None  # default: single-bus runs only
    controllers_file: str | Path | None = None
    interface: str | None = None  # EtherCAT NIC (default: prime_hardware.yaml)
    can_interface: str | None = None  # python-can interface (default: prime_hardware.yaml)
    can_channel: str | None = None
    sync0_period_s: float | None = None  # must equal 1/update_rate; only for an explicit cross-check
    unsafe_sync0_period_s: float | None = None  # bypasses the check: reproduces the 4616 fault on purpose
    bringup_rate: float | None = None  # Hz of the EtherCAT bring-up loop (default: prime_controllers.yaml)
    parallel_sdo: bool | None = None  # default: prime_controllers.yaml
    duration: float | None = None  # seconds of control loop after bringup; None = until stopped
    mode: Mode | None = None  # switch to this mode once up, and keep running
    sequence: Sequence[Mode] = ()  # modes to visit, one every ``dwell`` seconds, then stop
    dwell: float = 2.0
    truth_file: str | Path | None = None  # the virtual robot's wiring and factory offsets (emulation only)
    erob_config_dir: str | Path | None = None  # keep the folded per-slave configs here
    control_socket: str | Path | None = None
    ring_options: dict[str, Any] = field(default_factory=dict)  # emulator tunables


@dataclass
class Session:
    """Everything a running bringup holds; ``summary()`` is the report of the run."""

    robot: Robot
    config: ControllersConfig
    calibration: Calibration
    options: BringupOptions
    manager: ControllerManager
    ethercat: Any = None  # EthercatSystem
    sito: Any = None  # SitoSystem
    impedance: Any = None  # ImpedanceManager
    virtual: Any = None  # VirtualPrime
    stages: list[tuple[str, float]] = field(default_factory=list)
    bringup_seconds: float = 0.0
    faults: dict[str, str] = field(default_factory=dict)
    load_test: list[dict[str, Any]] = field(default_factory=list)
    gate_reset_failures: list[str] = field(default_factory=list)
    emulator: dict[str, Any] = field(default_factory=dict)  # the virtual Prime's own record, filled at teardown

    def mark_limp(self, joint: str, limp: bool) -> None:
        """In a broadcaster-only run: while ``limp``, give ``joint`` a finite target with zero stiffness, so its
        CSP target follows the actual position (no following error while it is swept); otherwise NaN again,
        no command, and the drive holds where it is."""
        self.manager.resources.command.position[self.robot.index(joint)] = 0.0 if limp else np.nan

    def summary(self) -> dict[str, Any]:
        stats = self.manager.stats.summary()
        slaves_op = 0
        ec_bringup = None
        if self.ethercat is not None and self.ethercat.master is not None:
            master = self.ethercat.master
            slaves_op = int(np.count_nonzero(np.asarray(master.al_state) & 0x0F == 0x08))
            ec_bringup = self.ethercat.bringup.as_dict() if self.ethercat.bringup is not None else None
        sito_online = 0
        if self.sito is not None:
            silent = {key.rsplit("/", 1)[-1] for key in self.sito.flags if "/rx_timeout/" in key}
            sito_online = len(self.robot.hardware.mit_joints) - len(silent)
        return {
            "backends": self.options.backends,
            "emulate": self.options.emulate,
            "update_rate_hz": self.manager.update_rate,
            "bringup_seconds": self.bringup_seconds,
            "stages": [{"name": name, "seconds": seconds} for name, seconds in self.stages],
            "ethercat_bringup": ec_bringup,
            "slaves_op": slaves_op,
            "sito_online": sito_online,
            "mode_switches": [r.as_dict() for r in self.impedance.reports] if self.impedance is not None else [],
            "modes_visited": list(self.manager.modes_visited),
            "ticks": stats["ticks"],
            "tick_us": stats["tick_us"],
            "jitter_us": stats["jitter_us"],
            "overruns": stats["overruns"],
            "fallbacks": list(self.manager.fallbacks),
            "faults": dict(self.faults),
            "load_test": list(self.load_test),
            "gate_reset_failures": list(self.gate_reset_failures),
            "emulator": dict(self.emulator),
        }


def _staged(stages: list[tuple[str, float]], name: str, since: float) -> float:
    now = time.monotonic()
    stages.append((name, now - since))
    return now


def open_session(options: BringupOptions, stack: contextlib.ExitStack) -> Session:
    """Bring Prime up as ``options`` says; everything opened is registered on ``stack`` for teardown."""
    if options.backends not in BACKENDS:
        raise PrimeError(f"backends must be one of {', '.join(BACKENDS)}, got {options.backends!r}")
    began = time.monotonic()
    stages: list[tuple[str, float]] = []
    robot = load_robot(options.hardware_file)
    config = load_controllers(robot.names, options.controllers_file)
    calibration = options.calibration or load_calibration(robot.hardware, options.calibration_file)
    update_rate = config.update_rate
    bringup_rate = options.bringup_rate or config.bringup_rate
    parallel = config.impedance.parallel_sdo if options.parallel_sdo is None else options.parallel_sdo
    use_ec = options.backends in ("all", "ec")
    use_can = options.backends in ("all", "can")

    from humanoid_prime.drivers.ethercat.master import sync0_period_ns

    sync0_period_ns(update_rate, sync0_period_s=options.sync0_period_s)  # refuse a mismatch before the bus
    t = _staged(stages, "configuration", began)

    emulator_record: dict[str, Any] = {}
    interface = options.interface or robot.hardware.ethercat.interface
    can_interface = options.can_interface
    can_channel = options.can_channel
    virtual = None
    if options.emulate:
        from humanoid_prime.sim.demo import START_POSE
        from humanoid_prime.virtual.harness import VirtualPrime

        virtual = stack.enter_context(VirtualPrime(hardware_file=options.hardware_file,
                                                   truth_file=options.truth_file, pose=START_POSE,
                                                   **options.ring_options))
        # Runs at teardown after everything opened later (gate reset, drives disabled), before the virtual
        # Prime goes away: what the drives themselves recorded.
        stack.callback(_record_emulator, virtual, emulator_record)
        interface = virtual.master_interface
        can_interface, can_channel = virtual.can_interface, virtual.can_channel
        t = _staged(stages, "virtual prime", t)

    components: list[HardwareComponent] = []
    ethercat = sito = None
    if use_ec:
        from humanoid_prime.drivers.ethercat.soem_master import SoemMaster
        from humanoid_prime.drivers.ethercat.system import EthercatSystem

        master = SoemMaster(interface, update_rate_hz=update_rate, bringup_rate_hz=bringup_rate,
                            sync0_period_s=options.sync0_period_s,
                            unsafe_sync0_period_s=options.unsafe_sync0_period_s, parallel_sdo=parallel)
        ethercat = EthercatSystem(robot, calibration, update_rate_hz=update_rate, bringup_rate_hz=bringup_rate,
                                  master=master, interface=interface, config_dir=options.erob_config_dir)
        components.append(ethercat)
    if use_can:
        from humanoid_prime.drivers.sito.system import SitoSystem

        sito = SitoSystem(robot, calibration, control_rate=update_rate, interface=can_interface,
                          channel=can_channel)
        components.append(sito)

    broadcaster_only = options.backends != "all" if options.broadcaster_only is None else options.broadcaster_only
    manager = ControllerManager(robot, components, config, update_rate=update_rate,
                                broadcaster_only=broadcaster_only)
    stack.callback(manager.shutdown)
    session = Session(robot, config, calibration, options, manager, ethercat, sito, virtual=virtual, stages=stages,
                      emulator=emulator_record)
    manager.topics.subscribe(SAFETY_STATUS, lambda status: _note_faults(session, status))
    manager.start()
    stages.extend(manager.stages)
    t = time.monotonic()
    manager.tick()  # the first read -> update -> write: joint states flow from here on
    t = _staged(stages, "first tick", t)
    session.bringup_seconds = t - began

    if ethercat is not None and not broadcaster_only:
        from humanoid_prime.runtime.impedance import ImpedanceManager

        impedance = ImpedanceManager(robot, ethercat.master, config.mode_gains(), parallel=parallel,
                                     retries=config.impedance.sdo_retries)
        session.impedance = impedance
        manager.add_flag_source(impedance)
        # Normally closed by run_loop while the loop still ticks; this covers an exception on the way.
        stack.callback(lambda: session.gate_reset_failures.extend(impedance.close()))
        # The bus is ready and joint states have flowed (the first tick); arm the gate and follow the mode.
        impedance.start(manager.topics, lambda: ethercat.bus_ready, timeout=5.0)
        _staged(stages, "impedance manager armed", t)
    return session


_GAIN_OBJECTS = {POS_LOOP_GAIN[0], VEL_LOOP_GAIN[0], BUS_GAIN_GATE[0]}


def _record_emulator(virtual: Any, record: dict[str, Any]) -> None:
    """The drives' final state and their log of gain-register writes, as the emulator saw them."""
    with contextlib.suppress(PrimeError):
        slaves = virtual.control.call("status")
        record["slaves"] = [{"position": s["position"], "al_state": s["al_state"],
                             "mailbox_faults": s["mailbox_faults"], "error_history": s["drive"]["error_history"],
                             **{k: s["drive"][k] for k in ("gate", "pos_reg", "vel_reg", "integral")}}
                            for s in slaves]
        record["sdo_log"] = [e for e in virtual.control.call("sdo_log") if e["index"] in _GAIN_OBJECTS]


def _note_faults(session: Session, status: SafetyStatus) -> None:
    for key, text in status.flags.items():
        session.faults.setdefault(key, text)


class ModeSequence:
    """Visits ``modes`` in order, one every ``dwell`` seconds, from the control loop's tick callback."""

    def __init__(self, modes: Sequence[Mode], dwell: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.modes = list(modes)
        self.dwell = dwell
        self.clock = clock
        self._next = clock()

    def __call__(self, manager: ControllerManager) -> None:
        if self.modes and self.clock() >= self._next:
            manager.request_mode(self.modes.pop(0))
            self._next = self.clock() + self.dwell

    @property
    def done(self) -> bool:
        return not self.modes


def run_loop(session: Session, stop: threading.Event,
             on_tick: Callable[[ControllerManager], None] | None = None) -> None:
    """The control-rate loop until ``stop``, the duration, or the end of the mode sequence plus one dwell."""
    options = session.options
    if options.mode is not None:
        session.manager.request_mode(options.mode)
    sequence = ModeSequence(options.sequence, options.dwell) if options.sequence else None
    deadline = None if options.duration is None else time.monotonic() + options.duration
    settle_until: list[float] = []

    def tick(manager: ControllerManager) -> None:
        if sequence is not None:
            sequence(manager)
            if sequence.done and not settle_until:
                settle_until.append(time.monotonic() + options.dwell)
        if on_tick is not None:
            on_tick(manager)
        now = time.monotonic()
        if (deadline is not None and now >= deadline) or (settle_until and now >= settle_until[0]
                                                          and options.duration is None):
            stop.set()

    session.manager.run(stop=stop, on_tick=tick)
    if session.impedance is not None:
        session.impedance.wait_idle(5.0)
        close_impedance_while_ticking(session)


def close_impedance_while_ticking(session: Session, timeout: float = 10.0) -> None:
    """Reset the eRob gain gate with the loop still running, so every drive keeps a live target (the
    active mode's, or the actual position while limp) at the moment its factory gains take over; a
    stopped loop would leave a stale target that the stiff factory gains snap to."""
    impedance = session.impedance
    done = threading.Event()

    def close() -> None:
        try:
            session.gate_reset_failures.extend(impedance.close())
        finally:
            done.set()

    threading.Thread(target=close, name="erob-gate-reset", daemon=True).start()
    deadline = time.monotonic() + timeout

    def until_done(manager: ControllerManager) -> None:
        if time.monotonic() > deadline:
            done.set()

    session.manager.run(stop=done, on_tick=until_done)


def measure_stiffness(session: Session, joints: Sequence[str], *, torque_nm: float = 5.0,
                      settle_s: float = 3.0, average_s: float = 1.0,
                      stop: threading.Event | None = None) -> list[dict[str, Any]]:
    """Load test on the virtual Prime: in STANDBY with gravity off in the plant, push each eRob joint with
    +torque and -torque and read the deflection; realised kp = 2*torque / (q(+) - q(-)).

    Runs in its own thread while the control loop runs; friction biases the figure low by about
    friction/torque (0.1/5 = 2 % on the eRob joints)."""
    if session.virtual is None:
        raise PrimeError("the load test needs the virtual Prime (--emulate): it pushes the plant")
    robot, manager, control = session.robot, session.manager, session.virtual.control
    for joint in joints:
        if joint not in robot.hardware.erob_slaves:
            raise PrimeError(f"load test: {joint!r} is not an eRob joint "
                             f"(eRob joints: {', '.join(robot.hardware.erob_joints)})")
    kp_nominal, _ = session.config.mode_gains()[Mode.STANDBY]
    efficiency = robot.hardware.torque_efficiency
    results = []

    stop = stop or threading.Event()

    def settle_and_average(i: int) -> float:
        if stop.wait(settle_s):
            raise PrimeError("load test stopped before it finished")
        samples = []
        end = time.monotonic() + average_s
        while time.monotonic() < end:
            samples.append(float(manager.resources.state.position[i]))
            time.sleep(0.01)
        return float(np.mean(samples))

    control.call("gravity", enabled=False)
    try:
        for joint in joints:
            i = robot.index(joint)
            control.call("push", joint=joint, torque_nm=torque_nm)
            q_plus = settle_and_average(i)
            control.call("push", joint=joint, torque_nm=-torque_nm)
            q_minus = settle_and_average(i)
            control.call("push", joint=joint, torque_nm=0.0)
            deflection = q_plus - q_minus
            kp = 2.0 * torque_nm / deflection if deflection > 0 else float("nan")
            ratio = kp / kp_nominal if kp_nominal > 0 else float("nan")
            results.append({"joint": joint, "torque_nm": torque_nm, "deflection_rad": deflection,
                            "kp_nominal": kp_nominal, "kp_realised": kp, "ratio": ratio,
                            "torque_efficiency": efficiency})
    finally:
        for joint in joints:
            with contextlib.suppress(PrimeError):
                control.call("push", joint=joint, torque_nm=0.0)
        control.call("gravity", enabled=True)
    return results


@contextlib.contextmanager
def stop_on_signals(stop: threading.Event):
    """SIGINT, SIGTERM and SIGHUP set ``stop``: the loop ends and everything is torn down in order (gate
    reset, drives disabled, wrists off). Later signals are ignored, so a second Ctrl-C cannot cut the
    teardown in half; every step of it is bounded by its own timeout. Enter this before the ExitStack that
    holds the session, so the handlers stay in place until the teardown is over."""
    previous = {}

    def handler(signum: int, frame: object) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        previous[sig] = signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def control_server(session: Session, path: str | Path | None) -> ControlServer:
    """The control socket: mode requests (full runs), SDO through this process's EtherCAT master, and in
    broadcaster-only runs the limp marker of ``prime limp``."""
    manager = session.manager
    request = None if manager.broadcaster_only else manager.request_mode
    sdo = session.ethercat.master if session.ethercat is not None else None
    joint_limp = on_close = None
    if manager.broadcaster_only and session.ethercat is not None:
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
                    sdo.sdo_write(position, *BUS_GAIN_GATE, struct.pack(BUS_GAIN_GATE_FORMAT, 0))
                session.faults[f"limp/ring{position}"] = (f"{ring_joints[position]} (ring {position}) was still "
                                                          "limp when the run ended; its gate was reset to 0")

    return ControlServer(request, path, sdo=sdo, joint_limp=joint_limp, on_close=on_close)
