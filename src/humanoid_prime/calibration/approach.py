"""The moving joint's motion, one control tick at a time (``calibration.auto`` runs it; DESIGN §5).

A ``JointRun`` is the joint being calibrated: its contact-effort cap, its approach gains, its leash, and its
effort feed-forward (``anchor`` measured before it moved, the model's change of gravity since, and the
``correction`` free motion teaches it). Its ``segment`` runs once per tick and sets the target and velocity:

- ``Hold``: stay (where it is, taking the effort it applies as the feed-forward, or at a target);
- ``Move``: ramp the target to a goal at the speed cap; a contact on the way fails it (leaving a stop, contacts
  count once the joint has lifted off);
- ``Approach``: toward a stop until contact, within the travel and time budgets; then press it with the leash
  while its position is recorded, ease the press and push with a velocity command while the effort is logged for
  the realised stiffness and damping.

``ContactDetector`` keeps the free-motion baseline of the lag and the effort, holds the target to the leash (the
target never leads the joint by more than its baseline lag plus ``leash``: ``CAP_SHARE`` of the cap at the most
stiffness the drive can realise, less what stopping from the speed cap costs), and sees contact: lag beyond the
baseline, no motion and a rise of effort, all together for ``DEBOUNCE_S``, never one sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MAX_SPEED_RAD_S = 0.2  # the speed cap: its default and its ceiling (DESIGN §5)
CAP_SHARE = 0.7  # the leash spends this share of the cap; the rest is margin (friction, the baseline's lag)
DAMPING_SHARE = 0.2  # of the cap, what stopping a joint moving at the speed cap may cost (kd * speed)
LEASH_RAD = 0.05  # how far beyond its free-motion lag the target may lead the joint at full cap
ACCEL_S = 0.5  # the target reaches the speed cap after this long
BASELINE_S = 0.1  # time constant of the free-motion baseline (lag and effort)
ADAPT_S = 0.5  # time constant with which free motion corrects the feed-forward (what the model got wrong)
DEBOUNCE_S = 0.06  # contact is every sign for this long, never one sample
EXCESS_SHARE = 0.5  # contact: the lag beyond its baseline exceeds this share of the leash,
STALL_SHARE = 0.25  # the joint moves at less than this share of the speed,
EFFORT_SHARE = 0.25  # and its effort rose by this share of the cap
SETTLE_S = 0.2  # at a stop, pressing with the full leash, before its position is averaged
AVERAGE_S = 0.1
DEPTH_RAMP = (1.0, 0.1)  # the press eases from and to these shares of the leash while the stiffness is measured,
DEPTH_RAMP_S = 0.6
SPEED_RAMP_S = 0.4  # then, at the lighter press, a velocity command into the stop rises to the speed cap
LIFT_RAD = 0.003  # a joint moving away from a stop has left it once it moved this far
TIME_MARGIN_S = 10.0  # a motion's time budget beyond its travel at the speed cap


def approach_gains(cap: float) -> tuple[float, float]:
    """(kp, kd) a joint approaches its stops with: kd such that stopping from the speed cap costs
    ``DAMPING_SHARE`` of the cap, kp such that the rest of ``CAP_SHARE`` is spent over ``LEASH_RAD``."""
    kd = DAMPING_SHARE * cap / MAX_SPEED_RAD_S
    kp = (CAP_SHARE - DAMPING_SHARE) * cap / LEASH_RAD
    return kp, kd



@dataclass
class Trace:
    """What the moving joint did, tick by tick, for the plot: time, position, commanded position, effort, and the
    contacts (time, position) and stops (time, position) found."""

    t: list[float] = field(default_factory=list)
    q: list[float] = field(default_factory=list)
    target: list[float] = field(default_factory=list)
    effort: list[float] = field(default_factory=list)
    contacts: list[tuple[float, float]] = field(default_factory=list)
    stops: list[tuple[float, float]] = field(default_factory=list)


@dataclass
class Tick:
    t: float
    dt: float
    q: float
    qd: float
    effort: float
    ff: float


class Segment:
    """One motion of the moving joint; ``update`` runs once per tick and sets ``target`` and ``velocity``."""

    finished = False
    failure: str | None = None

    def __init__(self, run: JointRun) -> None:
        self.run = run

    def update(self, tick: Tick) -> None:
        raise NotImplementedError

    def command(self) -> tuple[float, float] | None:
        """(target, velocity) this tick; None: no target yet."""
        raise NotImplementedError


class Hold(Segment):
    """Stay for ``average_s`` while the effort is averaged: where the joint is (``target`` None), taking the effort
    it applies now as the feed-forward, so holding moves nothing; or at ``target``. ``passive``: the joint stays
    held the way the others are (its drive's own gains, or the standby gains), as before it moves."""

    def __init__(self, run: JointRun, target: float | None = None, average_s: float = 0.0, *,
                 passive: bool = False) -> None:
        super().__init__(run)
        self.target = target
        self.velocity = 0.0
        self.average_s = average_s
        self.passive = passive
        self.efforts: list[float] = []
        self._since: float | None = None

    def command(self) -> tuple[float, float] | None:
        return None if self.target is None else (self.target, self.velocity)

    def update(self, tick: Tick) -> None:
        if self._since is None:
            self._since = tick.t
            if self.target is None:
                self.target = tick.q
                self.run.correction += tick.effort - tick.ff
        self.efforts.append(tick.effort)
        self.finished = tick.t - self._since >= self.average_s


class Move(Segment):
    """Ramp the target to ``goal`` at the speed cap with the leash on; a contact on the way is a failure.

    ``leaving`` a stop, its baseline is taken, and contacts watched for, once the joint has lifted off by
    ``LIFT_RAD``: until then the effort only falls from pressing the stop, which is no contact, and the target
    leads the joint (away from the stop) by at most twice the leash and what lifts its weight off a stop it rests
    on, never more."""

    def __init__(self, run: JointRun, goal: float, start: float, *, leaving: bool = False) -> None:
        super().__init__(run)
        self.goal = goal
        self.target = start
        self.side = 1 if goal >= start else -1
        self.velocity = 0.0
        self.detector = ContactDetector(run, self.side)
        self.budget_s = abs(goal - start) / run.speed + ACCEL_S + TIME_MARGIN_S
        self._leaving = leaving
        self._from: float | None = None
        self._t0: float | None = None
        self._reached: float | None = None

    def command(self) -> tuple[float, float]:
        return self.target, self.velocity

    def update(self, tick: Tick) -> None:
        run = self.run
        if self._t0 is None or self._from is None:
            self._t0, self._from = tick.t, tick.q
            self.detector.start(tick, self.target)
        if tick.t - self._t0 > self.budget_s:
            self.failure = f"did not reach {self.goal:+.3f} rad within {self.budget_s:.0f} s (at {tick.q:+.3f})"
            return
        if self._leaving and self.side * (tick.q - self._from) >= LIFT_RAD:
            self._leaving = False
            self.detector.start(tick, self.target)  # free of the stop: the baseline from here
        speed = run.speed * min(1.0, (tick.t - self._t0 + tick.dt) / ACCEL_S)
        remaining = self.side * (self.goal - self.target)
        step = min(speed * tick.dt, max(remaining, 0.0))
        wanted = self.target + self.side * step
        if self._leaving:
            most = self.side * tick.q + 2.0 * run.leash + run.weight / run.kp_leash  # it may have to lift its weight
            limited = wanted if self.side * wanted <= most else self.side * most
        else:
            limited = self.detector.leash(tick, wanted)
        self.velocity = self.side * speed if limited == wanted and remaining > 0 else 0.0
        self.target = limited
        if self._leaving:
            return
        if self.detector.update(tick, self.target, free=limited == wanted):
            self.failure = f"touched something at {tick.q:+.3f} rad while moving to {self.goal:+.3f} rad"
            return
        if self._reached is None and self.side * (self.goal - self.target) <= 1e-9:
            self._reached = tick.t
        if self._reached is not None:
            settled = abs(tick.q - self.goal) < 0.25 * run.leash + 0.01 and abs(tick.qd) < 0.25 * run.speed
            self.finished = settled or tick.t - self._reached > 2.0


class ContactDetector:
    """The free-motion baseline of the moving joint's lag and effort, the leash on its target, and contact:
    lag beyond the baseline, no motion and a rise of effort, all together for ``DEBOUNCE_S``."""

    def __init__(self, run: JointRun, side: int) -> None:
        self.run = run
        self.side = side
        self.lag_base = 0.0
        self.effort_base = 0.0
        self.count = 0
        self.needed = max(3, math.ceil(DEBOUNCE_S * run.rate - 1e-9))

    def start(self, tick: Tick, target: float) -> None:
        s = self.side
        self.lag_base = s * (target - tick.q)
        self.effort_base = s * (tick.effort - tick.ff)

    def leash(self, tick: Tick, wanted: float) -> float:
        """``wanted``, held back so the target leads the joint by at most its baseline lag plus the leash."""
        s = self.side
        most = s * tick.q + self.lag_base + self.run.leash
        return wanted if s * wanted <= most else s * most

    def update(self, tick: Tick, target: float, *, free: bool) -> bool:
        """Take this tick's measurements; True once contact has held for the debounce time."""
        run, s = self.run, self.side
        lag = s * (target - tick.q)
        effort = s * (tick.effort - tick.ff)
        excess = lag - self.lag_base
        rise = effort - self.effort_base
        if free and excess < 0.5 * EXCESS_SHARE * run.leash:
            alpha = min(1.0, tick.dt / BASELINE_S)
            self.lag_base += alpha * (lag - self.lag_base)
            self.effort_base += alpha * (effort - self.effort_base)
            run.adapt(tick, target)
        touching = (excess >= EXCESS_SHARE * run.leash and s * tick.qd <= STALL_SHARE * run.speed
                    and rise >= EFFORT_SHARE * run.cap)
        self.count = self.count + 1 if touching else 0
        return self.count >= self.needed

    def rise(self, tick: Tick) -> float:
        return self.side * (tick.effort - tick.ff) - self.effort_base


class Approach(Segment):
    """Toward the stop on ``side`` until contact (within the travel and time budgets), then press it with the
    leash while its position is recorded and the effort is measured at several depths and speeds."""

    def __init__(self, run: JointRun, side: int, start: float, budget_rad: float, measure: bool) -> None:
        super().__init__(run)
        self.side = side
        self.target = start
        self.start_target = start
        self.velocity = 0.0
        self.budget_rad = budget_rad
        self.budget_s = budget_rad / run.speed + ACCEL_S + TIME_MARGIN_S
        self.measure = measure
        self.detector = ContactDetector(run, side)
        self.phase = "moving"  # then settling (its position recorded), easing and pushing (measured), done
        self.stop: float | None = None
        self.points: list[tuple[float, float, float]] = []  # (lag, speed command, effort) into the stop, per tick
        self.peak = 0.0
        self._t0: float | None = None
        self._phase_t = 0.0
        self._positions: list[float] = []
        self._last: tuple[float, float] | None = None
        self.free: list[tuple[float, float]] = []  # (q, effort) in free motion, for the gravity fit

    def command(self) -> tuple[float, float]:
        return self.target, self.velocity

    def update(self, tick: Tick) -> None:
        run, s = self.run, self.side
        if self._t0 is None:
            self._t0 = tick.t
            self.detector.start(tick, self.target)
        if tick.t - self._t0 > self.budget_s:
            self.failure = (f"no stop on the {'upper' if s > 0 else 'lower'} side within {self.budget_s:.0f} s "
                            f"({run.speed:g} rad/s)")
            return
        if self.phase == "moving":
            speed = run.speed * min(1.0, (tick.t - self._t0 + tick.dt) / ACCEL_S)
            wanted = self.target + s * speed * tick.dt
            if s * (wanted - self.start_target) > self.budget_rad:
                wanted = self.start_target + s * self.budget_rad
                if s * (self.target - self.start_target) >= self.budget_rad - 1e-9 and abs(tick.qd) < 0.01:
                    self.failure = (f"no stop within {self.budget_rad:.2f} rad toward the "
                                    f"{'upper' if s > 0 else 'lower'} side (the range plus a margin)")
                    return
            limited = self.detector.leash(tick, wanted)
            free = limited == wanted
            self.velocity = s * speed if free else 0.0
            self.target = limited
            if free and tick.t - self._t0 > ACCEL_S:
                self.free.append((tick.q, tick.effort))
            if self.detector.update(tick, self.target, free=free):
                self.phase = "settling"
                self._phase_t = tick.t
                run.trace.contacts.append((tick.t, tick.q))
            return
        self.peak = max(self.peak, self.detector.rise(tick))
        if self.phase == "settling":
            self._press(tick, DEPTH_RAMP[0], 0.0)
            if tick.t - self._phase_t >= SETTLE_S:
                self._positions.append(tick.q)
            if tick.t - self._phase_t >= SETTLE_S + AVERAGE_S - 1e-9:
                self.stop = float(np.mean(self._positions))
                run.trace.stops.append((tick.t, self.stop))
                self._next("easing" if self.measure else "done", tick)
        elif self.phase == "easing":
            share = min(1.0, (tick.t - self._phase_t) / DEPTH_RAMP_S)
            self._press(tick, DEPTH_RAMP[0] + share * (DEPTH_RAMP[1] - DEPTH_RAMP[0]), 0.0)
            if share >= 1.0:
                self._next("pushing", tick)
        elif self.phase == "pushing":
            share = min(1.0, (tick.t - self._phase_t) / SPEED_RAMP_S)
            self._press(tick, DEPTH_RAMP[1], share * run.speed)
            if share >= 1.0:
                self._next("done", tick)
        if self.phase == "done":
            self.velocity = 0.0
            self.finished = True

    def _press(self, tick: Tick, depth: float, speed: float) -> None:
        """Press with ``depth`` of the leash and ``speed`` into the stop; the effort measured now answers the
        command of the last tick, so it is paired with that (lag taken at the position now)."""
        run, s = self.run, self.side
        if self._last is not None and self.phase != "settling":
            target, velocity = self._last
            self.points.append((s * (target - tick.q), s * velocity, s * (tick.effort - tick.ff)))
        self.target = tick.q + s * (self.detector.lag_base + depth * run.leash)
        self.velocity = s * speed
        self._last = (self.target, self.velocity)

    def _next(self, phase: str, tick: Tick) -> None:
        self.phase = phase
        self._phase_t = tick.t
        self._last = None

    def unloaded(self, q: float) -> float:
        """The target that stops pressing the joint at ``q``: its free-motion lag, no more."""
        return q + self.side * self.detector.lag_base


class JointRun:
    """The moving joint's settings and its per-tick command (loop thread)."""

    def __init__(self, index: int, name: str, *, cap: float, gains: tuple[float, float],
                 leash_gains: tuple[float, float], speed: float, rate: float, effort_limit: float) -> None:
        self.index = index
        self.name = name
        self.cap = cap
        self.kp, self.kd = gains
        kp_leash, kd_leash = leash_gains
        self.speed = speed
        self.rate = rate
        self.effort_limit = effort_limit
        self.kp_leash = kp_leash
        self.leash = (CAP_SHARE * cap - kd_leash * speed) / kp_leash
        self.trace = Trace()
        self.segment: Segment | None = None
        self.anchor = 0.0  # holding effort measured before moving
        self.gravity0 = 0.0  # the model's gravity torque there (host frame)
        self.correction = 0.0  # what free motion has taught the feed-forward (Nm)
        self.weight = 0.0  # the most gravity the model puts on the joint over its travel (Nm)
        self.budget = math.inf  # the most the target travels from the start toward a stop (rad)
        self.bounds = (-math.inf, math.inf)  # where the target may go (the travel budget around the start)
        self.refused: str | None = None  # why the gate refused its command (None: it never did)

    @property
    def active(self) -> bool:
        """Commanded by its own segment: not held the way the other joints are (before and after it moves)."""
        segment = self.segment
        return not (isinstance(segment, Hold) and segment.passive)

    def feed_forward(self, gravity: float) -> float:
        """The effort feed-forward (Nm, host frame) where the model puts ``gravity`` on the joint: the holding effort
        measured before it moved, the model's change of gravity since, what free motion taught it; within the
        joint's effort limit."""
        ff = self.anchor + gravity - self.gravity0 + self.correction
        return min(max(ff, -self.effort_limit), self.effort_limit)

    def adapt(self, tick: Tick, target: float) -> None:
        """In free motion, move the steady lag into the feed-forward: the model's gravity is only as good as the
        calibration it is evaluated with, which is what is being found (a flipped joint's is mirrored)."""
        step = tick.dt / ADAPT_S * self.kp_leash * (target - tick.q)
        self.correction = min(max(self.correction + step, -self.effort_limit), self.effort_limit)
