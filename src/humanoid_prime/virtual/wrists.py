"""The virtual Prime's Sito wrists in a process of their own, coupled to the plant through shared memory.

On the robot the wrists' firmware and the eRob's ESCs answer in parallel, each on its own silicon. In one
emulator process they would take turns under one interpreter lock, and at a 1 kHz control rate the wrists'
bus work (four commands in, eight feedback frames out, and on the emulated bus the host's and our own frames
read back) would hold EtherCAT replies back by hundreds of microseconds. So the wrists run in a child
process, forked from the virtual Prime once its world is built:

- the child owns the CAN bus and the four ``SitoMotor`` firmwares: it parses every frame, keeps their state,
  streams their feedback at their intervals and publishes what each firmware's MIT law acts on
  (``SitoMotor.law()``) into shared memory after every firmware tick;
- the parent owns the plant: at every physics step it evaluates each wrist's law (``mit_torque``) on the
  wrist's state at that step, exactly as the firmware law ran before, and publishes the wrists' joint state
  for the child's feedback and for holding position on enable.

A law published between two physics steps takes effect at the next one, as a frame the firmware receives
between two of its ticks does. Fault injection (silent, dropped frames, garbage) travels over a pipe.
The child exits when the parent does (the pipe closes), ignores Ctrl-C (the parent stops it), and reports a
bus it cannot open back to the parent, which refuses to start.
"""

from __future__ import annotations

import contextlib
import gc
import multiprocessing
import os
import signal
from collections.abc import Mapping
from multiprocessing.connection import Connection
from typing import Any

import can
import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.errors import PrimeError
from humanoid_prime.virtual.plant import MujocoPlant, Plant, PrimeWorld
from humanoid_prime.virtual.sito import FAULTS, SitoEmulator, SitoMotor, mit_torque

LAW_FIELDS = 6  # SitoMotor.law(): enabled, position target, velocity target, kp, kd, feed-forward
_START_TIMEOUT_S = 20.0


class SharedWrists:
    """The wrists' joint state (parent to child) and their firmwares' law inputs (child to parent), in one
    block of shared memory created before the fork."""

    def __init__(self, n: int) -> None:
        self.n = n
        self._block = multiprocessing.RawArray("d", n * (2 + LAW_FIELDS))
        array = np.frombuffer(self._block, dtype=np.float64)
        self.q = array[:n]
        self.qd = array[n:2 * n]
        self.law = array[2 * n:].reshape(n, LAW_FIELDS)

    def publish_law(self, motors: list[SitoMotor]) -> None:
        for motor in motors:
            self.law[motor.index] = motor.law()


class SharedStatePlant(Plant):
    """The child's view of the wrists: joint state read from shared memory, moved by the parent's plant."""

    def __init__(self, shared: SharedWrists) -> None:
        super().__init__(shared.n)
        self.q = shared.q
        self.qd = shared.qd

    def step(self, torque: np.ndarray, braked: np.ndarray, dt: float) -> None:
        """Nothing to integrate here: the parent applies the law at each of its physics steps."""


class WristProcess:
    """Runs the Sito motors of ``robot`` in a child process on the python-can bus ``can.Bus(**bus)``;
    ``step`` is the world's stepper in the parent (``world.attach(wrists.step)``)."""

    def __init__(self, robot: Robot, world: PrimeWorld, *, bus: Mapping[str, Any], rate_hz: float,
                 priority: int | None = None) -> None:
        self.robot = robot
        self.world = world
        self.view: MujocoPlant = world.plant(robot.hardware.sito_joints)
        self.limits = [robot.joints[robot.index(j)].effort_limit for j in robot.hardware.sito_joints]
        self.shared = SharedWrists(self.view.n)
        self._torque = np.zeros(self.view.n)
        self._unbraked = np.zeros(self.view.n, dtype=bool)  # a Sito has no brake
        self._options = {"bus": dict(bus), "rate_hz": rate_hz, "priority": priority}
        self._publish_state()
        self._process: Any = None
        self._conn: Connection | None = None

    def start(self) -> None:
        """Fork the child and wait until its bus is open; PrimeError with the child's reason otherwise."""
        context = multiprocessing.get_context("fork")
        ours, theirs = context.Pipe()
        self._process = context.Process(target=_child, name="virtual-prime-wrists", daemon=True,
                                        args=(theirs, ours, self.robot, self.shared, self._options))
        self._process.start()
        theirs.close()
        self._conn = ours
        if not ours.poll(_START_TIMEOUT_S):
            self.close()
            raise PrimeError(f"the emulated Sito wrists did not start within {_START_TIMEOUT_S:.0f} s")
        try:
            ready = ours.recv()
        except EOFError:
            ready = {"error": f"the emulated Sito wrists' process exited ({self._process.exitcode})"}
        if "error" in ready:
            self.close()
            raise PrimeError(ready["error"])

    def step(self, dt: float) -> None:
        """One physics step of the world with each wrist's firmware law applied at the wrist's state now."""
        view = self.view
        torque = self._torque
        for k, (law, q, qd) in enumerate(zip(self.shared.law.tolist(), view.q.tolist(), view.qd.tolist(),
                                             strict=True)):
            torque[k] = mit_torque(law, q, qd, self.limits[k])
        view.step(torque, self._unbraked, dt)
        self.world.step(dt)
        self._publish_state()

    def _publish_state(self) -> None:
        self.shared.q[:] = self.view.q
        self.shared.qd[:] = self.view.qd

    def configure(self, can_id: int, **faults: Any) -> dict[str, Any]:
        """Set fault injection on the motor at ``can_id`` (``silent``, ``drop_fraction``, ``garbage``; None
        leaves one as it is); returns the motor's faults as they are now."""
        unknown = set(faults) - set(FAULTS)
        if unknown:
            raise TypeError(f"unknown Sito fault {sorted(unknown)[0]!r} (known: {', '.join(FAULTS)})")
        if self._conn is None:
            raise PrimeError("the emulated Sito wrists are not running")
        try:
            self._conn.send({"can_id": can_id, **{k: v for k, v in faults.items() if v is not None}})
            reply = self._conn.recv()
        except (EOFError, OSError) as exc:
            raise PrimeError(f"the emulated Sito wrists' process is gone ({exc or 'pipe closed'})") from None
        if "error" in reply:
            raise KeyError(reply["error"])
        return reply

    def close(self) -> int | None:
        """Stop the child and return its exit code (None when it never started)."""
        if self._process is None:
            return None
        if self._conn is not None:
            with contextlib.suppress(OSError):
                self._conn.send(None)
            self._conn.close()
            self._conn = None
        self._process.join(5.0)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(5.0)
        code = self._process.exitcode
        self._process = None
        return code


def _child(conn: Connection, parents_end: Connection, robot: Robot, shared: SharedWrists,
           options: dict[str, Any]) -> None:
    parents_end.close()  # so that the parent's death closes the pipe for us
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group; the parent stops us
    if options["priority"] is not None:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(options["priority"]))
    where = ":".join(str(v) for v in options["bus"].values())
    try:
        bus = can.Bus(**options["bus"])
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        conn.send({"error": f"cannot open the Sito bus {where}: {exc}"})
        return
    try:
        emulator = SitoEmulator.for_robot(robot, bus, SharedStatePlant(shared), rate_hz=options["rate_hz"])
    except ValueError as exc:
        bus.shutdown()
        conn.send({"error": f"cannot emulate the Sito motors: {exc}"})
        return
    motors = list(emulator.motors.values())
    emulator.world_step = lambda _dt: shared.publish_law(motors)  # after each firmware tick
    gc.collect()
    gc.freeze()
    emulator.start()
    try:
        conn.send({"ready": True})
        _serve(conn, emulator)
    finally:
        emulator.stop()
        bus.shutdown()


def _serve(conn: Connection, emulator: SitoEmulator) -> None:
    """Answer fault-injection requests until the parent says stop or goes away."""
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        try:
            conn.send(emulator.inject(**request))
        except KeyError as exc:
            conn.send({"error": str(exc.args[0])})
