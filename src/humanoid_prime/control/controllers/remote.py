"""REMOTE: follow an external MIT command streamed on ``/remote_policy_controller/command``."""

from __future__ import annotations

import threading

import numpy as np

from humanoid_prime.config.robot import Robot
from humanoid_prime.control._tick import OK, SHAPE, Inbox
from humanoid_prime.control.bounds import CommandBounds
from humanoid_prime.control.controller import Controller, gain_rows
from humanoid_prime.control.flags import Level
from humanoid_prime.control.interfaces import COMMAND_NAMES, CommandArrays, StateArrays
from humanoid_prime.control.topics import REMOTE_COMMAND, MitCommand, TopicBus
from humanoid_prime.modes import Mode


class RemotePolicyController(Controller):
    """Applies the latest accepted ``MitCommand`` every tick.

    A message is rejected (counted in ``rejected``, flagged while REMOTE is active) unless ``joint_names`` is
    exactly the canonical joint list, every array has one value per joint and the five rows are within the
    command bounds (control/bounds.py, the manager's own). A rejected message changes nothing: the last accepted
    command (or the stale policy) goes on. Messages come from any thread (in-process, DDS).

    The eRob entries of the incoming stiffness and damping are replaced by the mode's fixed eRob gains
    (``erob_kp``, ``erob_kd``): eRob impedance is written once per mode over SDO, so only the Sito wrists take
    the message's per-tick gains.

    Freshness is arrival time, in the manager's clock at tick resolution. On entry nothing is fresh:
    messages that arrived while inactive are dropped. When no message arrived for longer than
    ``timeout`` the stale policy applies: ``damp`` targets the live position with zero velocity and
    effort, Sito joints get stiffness 0 and damping ``stale_kd`` (6), eRob joints keep the mode gains,
    which with a target on the live position act as a damper too; ``hold`` keeps the last command
    (and damps until a first command arrives).
    """

    def __init__(self, topic: str = REMOTE_COMMAND, timeout: float = 0.1, stale_policy: str = "damp",
                 stale_kd: float = 6.0, erob_kp: float = 20.0, erob_kd: float = 2.0) -> None:
        super().__init__(Mode.REMOTE.controller, Mode.REMOTE)
        if stale_policy not in ("damp", "hold"):
            raise ValueError(f"stale_policy must be 'damp' or 'hold', got {stale_policy!r}")
        self.topic = topic
        self.timeout = timeout
        self.stale_policy = stale_policy
        self.stale_kd = stale_kd
        self.erob_kp = erob_kp
        self.erob_kd = erob_kd
        self.accepted = 0
        self.rejected = 0
        self.last_rejection = ""

    def on_configure(self, robot: Robot, topics: TopicBus) -> None:
        self.names = robot.names
        self._erob = np.array([j.family == "erob" for j in robot.joints])
        self._sito = ~self._erob
        # Stale-damp gains; their eRob entries are also the fixed mode gains applied to every message.
        self._damp_kp, self._damp_kd = gain_rows(robot, (self.erob_kp, self.erob_kd), (0.0, self.stale_kd))
        self._lock = threading.Lock()
        self._inbox = np.zeros((5, robot.n))
        self._bounds = CommandBounds(robot)  # the manager's bounds; a check of its own, used under the lock
        self._take = Inbox(self._inbox, self._bounds.check).take
        self._current = np.zeros((5, robot.n))
        self._fresh = False
        self._has_command = False
        self._arrival = 0.0
        self._stale = False
        self._rejections_seen = 0
        topics.subscribe(self.topic, self._on_message)

    def _on_message(self, message: MitCommand) -> None:
        rows = [getattr(message, name) for name in COMMAND_NAMES]
        names = tuple(message.joint_names)
        with self._lock:
            found = self._take(*rows) if names == self.names else None
            if found == OK:
                self._fresh = True
                self.accepted += 1
                return
            self.rejected += 1
            self.last_rejection = self._refusal(names, rows, found)

    def _refusal(self, names: tuple[str, ...], rows: list[object], found: int | None) -> str:
        """Why a message was refused: its joint names (``found`` None), the shape of a row, or the bound it
        broke (where ``Inbox.take`` left ``row`` and ``col``)."""
        if found is None:
            if len(names) != len(self.names):
                return f"{len(names)} joint names, expected {len(self.names)} in canonical order"
            i = next(i for i, (got, want) in enumerate(zip(names, self.names, strict=True)) if got != want)
            return f"joint {i} is {names[i]!r}, expected {self.names[i]!r} (canonical order)"
        row, col = self._bounds.check.row, self._bounds.check.col
        if found == SHAPE:
            try:
                values = np.asarray(rows[row], dtype=np.float64)
            except (TypeError, ValueError) as exc:
                return f"{COMMAND_NAMES[row]} is not a list of numbers ({exc})"
            return f"{COMMAND_NAMES[row]} has shape {values.shape}, expected ({len(self.names)},)"
        return self._bounds.refusal(found, row, col, float(np.asarray(rows[row], dtype=np.float64)[col]))

    def on_activate(self, state: StateArrays, now: float) -> None:
        with self._lock:
            self._fresh = False
            self._rejections_seen = self.rejected
        self._has_command = False
        self._stale = False

    def on_deactivate(self) -> None:
        self.clear_flag("stale")
        self.clear_flag("rejected")

    def update(self, now: float, dt: float, state: StateArrays, command: CommandArrays) -> None:
        with self._lock:
            if self._fresh:
                np.copyto(self._current, self._inbox)
                self._fresh = False
                self._has_command = True
                self._arrival = now
                self.clear_flag("rejected")
            if self.rejected != self._rejections_seen:
                self._rejections_seen = self.rejected
                self.set_flag("rejected", f"rejected command #{self.rejected} on {self.topic}: {self.last_rejection}",
                              Level.WARN)
        stale = not self._has_command or now - self._arrival > self.timeout
        if stale != self._stale:
            self._stale = stale
            if stale and not self._has_command:
                self.set_flag("stale", f"waiting for the first command on {self.topic}; damping meanwhile", Level.WARN)
            elif stale:
                self.set_flag("stale", f"no command on {self.topic} for more than {self.timeout * 1000:.0f} ms; "
                                       f"{self.stale_policy} until the next one", Level.WARN)
            else:
                self.clear_flag("stale")
        if stale and (self.stale_policy == "damp" or not self._has_command):
            np.copyto(command.position, state.position)
            # a limp wrist measured beyond a limit gets its target on the limit (every target must be within)
            np.clip(command.position, self._bounds.lower, self._bounds.upper, out=command.position, where=self._sito)
            command.data[1:3] = 0.0
            np.copyto(command.stiffness, self._damp_kp)
            np.copyto(command.damping, self._damp_kd)
            return
        np.copyto(command.data, self._current)
        np.copyto(command.stiffness, self._damp_kp, where=self._erob)
        np.copyto(command.damping, self._damp_kd, where=self._erob)
