"""The moving joint's motion, one control tick at a time (``calibration.auto`` runs it; DESIGN §5).

A ``JointRun`` is a joint being calibrated: its contact-effort cap, its approach gains, its leash, its speeds and
its effort feed-forward (``anchor`` measured before it moved, the model's change of gravity since, the
``correction`` free motion teaches it, and its inertia times the target's acceleration). Its ``segment`` runs
once per tick and sets the target and velocity:

- ``Hold``: stay (where it is, taking the effort it applies as the feed-forward, or at a target) until the joint
  is still (``contact.Still``), measured, not a fixed wait;
- ``Move``: the target to a goal at the travel speed, where no stop can be; a contact on the way fails it
  (leaving a stop, contacts count once the joint has lifted off). Back across what an approach has just crossed
  at the contact speed, faster (``CROSSED``), with the feed-forward it needed at each point there (``Taught``);
- ``Approach``: toward a stop along its ``plan.Search``: at the travel speed where no stop can be, slowed
  ``SLOW_LEAD_RAD`` before each window where the stop may lie to ``SEARCH_SHARE`` of the contact speed (at most
  ``MAX_SPEED_RAD_S``, a ceiling); at contact, press it with the leash until it is still, its position averaged
  there; with ``measure``, then ease the press and push with a velocity command while the effort is logged
  (realised stiffness and damping).

The travel speed is the regime's: a robot's prior gives the joint's frame (``TRAVEL[True]``), its first stop has
found it (``FOUND``), or neither (the contact speed). The target's speed rises at most at the joint's acceleration
(``accel_for``: what a share of its cap gives its inertia, no more than the regime's) and falls so that it is at
the search speed before a window. Each tick's time is counted by what the joint did (``KINDS``): for the report
and the plot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from humanoid_prime.calibration.contact import ContactDetector, Still, Tick
from humanoid_prime.calibration.plan import Search

MAX_SPEED_RAD_S = 0.2  # the contact speed: its default and its ceiling (DESIGN §5)
# Where no stop can be: the travel speed and the most the target's speed changes per second, where the joint's
# frame is known from a robot's prior calibration (the model's gravity and inertia hold) and where it is not (the
# feed-forward is what free motion teaches, at the contact speed: faster, a joint overshoots its target by what the
# model got wrong, and meets a stop faster than the contact speed, or stalls short of it).
TRAVEL = {True: (2.5, 6.0), False: (MAX_SPEED_RAD_S, 1.0)}
# A new robot's joint, once its first stop has told its offset (its arm's bodies checked under every direction its
# joints may still have, ``calibration.auto``): the model's gravity holds but for those directions, so it travels
# slower than where a robot's prior gives its frame, and brakes gently (at 1.5 rad/s and 4 rad/s^2 a shoulder ran
# 0.09 rad ahead of its target on the virtual Prime in real time, its arm's weight pulling it on).
FOUND = (1.0, 2.0)
# Back across what a joint has just crossed at the contact speed (everything else held where it was: the same
# ground, clear), with the feed-forward it needed there at each point (``Taught``) instead of the model's.
CROSSED = (1.5, 3.0)
ACCEL_SHARE = 0.5  # of the cap: the most accelerating the joint's inertia may ask (it is fed forward)
# Within a window the target moves at ``SEARCH_SHARE`` of the contact speed, and a joint faster than
# ``GOVERN_SHARE`` of it holds its target back: a joint follows its target's speed only within some 10 % (its drive's
# loop, its encoder's resolution), and the contact speed is a ceiling, not an aim.
SEARCH_SHARE = 0.85
GOVERN_SHARE = 0.9
SLOW_LEAD_RAD = 0.1  # the target is at the contact speed this far before a window (the joint settles meanwhile)
CAP_SHARE = 0.7  # the leash spends this share of the cap; the rest is margin (friction, the baseline's lag)
DAMPING_SHARE = 0.2  # of the cap, what stopping a joint moving at the contact speed may cost (kd * speed)
LEASH_RAD = 0.05  # how far beyond its free-motion lag the target may lead the joint at full cap
ADAPT_S = 0.5  # time constant with which free motion corrects the feed-forward (what the model got wrong)
SETTLE_TIMEOUT_S = 1.0  # pressing a stop, the joint is still within this, or its last readings are the stop
DEPTH_RAMP = (1.0, 0.1)  # the press eases from and to these shares of the leash while the stiffness is measured,
DEPTH_RAMP_S = 0.6
SPEED_RAMP_S = 0.4  # then, at the lighter press, a velocity command into the stop rises to the contact speed
YIELD_RAD = 0.005  # pressed after a contact, a joint that goes on this far met no stop (it had run ahead of its target)
LIFT_RAD = 0.003  # a joint moving away from a stop has left it once it moved this far
TIME_MARGIN_S = 10.0  # a motion's time budget beyond its travel
KINDS = ("travel", "search", "settle", "push", "question")  # what each tick of a joint's time went to


def approach_gains(cap: float) -> tuple[float, float]:
    """(kp, kd) a joint approaches its stops with: kd such that stopping from the contact speed costs
    ``DAMPING_SHARE`` of the cap, kp such that the rest of ``CAP_SHARE`` is spent over ``LEASH_RAD``."""
    kd = DAMPING_SHARE * cap / MAX_SPEED_RAD_S
    kp = (CAP_SHARE - DAMPING_SHARE) * cap / LEASH_RAD
    return kp, kd


def accel_for(cap: float, inertia: float, most: float) -> float:
    """The acceleration (rad/s^2) a joint of ``inertia`` (kg m^2, about its axis) moves with, at most ``most``."""
    return min(most, ACCEL_SHARE * cap / inertia) if inertia > 0 else most


@dataclass
class Trace:
    """What the moving joint did, tick by tick, for the plot: time, position, commanded position, effort, what
    the tick went to (``KINDS``), and the contacts (time, position) and stops (time, position) found."""

    t: list[float] = field(default_factory=list)
    q: list[float] = field(default_factory=list)
    target: list[float] = field(default_factory=list)
    effort: list[float] = field(default_factory=list)
    kind: list[str] = field(default_factory=list)
    contacts: list[tuple[float, float]] = field(default_factory=list)
    stops: list[tuple[float, float]] = field(default_factory=list)


class Segment:
    """One motion of the moving joint; ``update`` runs once per tick and sets ``target``, ``velocity`` and the
    target's ``accel``."""

    finished = False
    failure: str | None = None
    kind = "settle"
    accel = 0.0

    def __init__(self, run: JointRun) -> None:
        self.run = run

    def update(self, tick: Tick) -> None:
        raise NotImplementedError

    def command(self) -> tuple[float, float] | None:
        """(target, velocity) this tick; None: no target yet."""
        raise NotImplementedError


class Ramp:
    """The target's speed along one direction: it rises by at most the joint's acceleration per second, never
    beyond the limit where the target is, and falls to it at once."""

    def __init__(self, accel: float) -> None:
        self.most = accel
        self.speed = 0.0
        self.accel = 0.0

    def step(self, dt: float, limit: float) -> float:
        """This tick's speed under ``limit``; the distance it covers is ``speed * dt``."""
        speed = max(0.0, min(self.speed + self.most * dt, limit))
        self.accel, self.speed = (speed - self.speed) / dt, speed
        return speed

    def held(self, covered: float, dt: float) -> None:
        """The leash let the target cover only ``covered``: that was its speed."""
        speed = max(0.0, covered / dt)
        if speed < self.speed:
            self.speed, self.accel = speed, 0.0


def braking(speed: float, distance: float, accel: float) -> float:
    """The most speed from which ``accel`` brings a target to ``speed`` within ``distance``."""
    return math.sqrt(speed * speed + 2.0 * accel * max(distance, 0.0))


class Hold(Segment):
    """Stay until the joint is still: where it is (``target`` None), taking the effort it applies now as the
    feed-forward, so holding moves nothing; or at ``target``. ``passive``: the joint stays held the way the others
    are (its drive's own gains, or the standby gains), as before it moves; ``efforts`` are what it applied."""

    def __init__(self, run: JointRun, target: float | None = None, *, passive: bool = False) -> None:
        super().__init__(run)
        self.target = target
        self.velocity = 0.0
        self.passive = passive
        self.efforts: list[float] = []
        self._still = Still()
        self._began = False

    def command(self) -> tuple[float, float] | None:
        return None if self.target is None else (self.target, self.velocity)

    def update(self, tick: Tick) -> None:
        if not self._began:
            self._began = True
            if self.target is None:
                self.target = tick.q
                self.run.correction += tick.effort - tick.ff
        self.efforts.append(tick.effort)
        self.finished = self._still.update(tick.q, tick.qd)


class Move(Segment):
    """The target to ``goal`` at the travel speed, with the leash on; a contact on the way is a failure.

    ``leaving`` a stop, its baseline is taken, and contacts watched for, once the joint has lifted off by
    ``LIFT_RAD``: until then the effort only falls from pressing the stop, which is no contact, and the target
    leads the joint (away from the stop) by at most twice the leash and what lifts its weight off a stop it rests
    on, never more. ``kind``: what its time is counted as."""

    def __init__(self, run: JointRun, goal: float, start: float, *, leaving: bool = False,
                 kind: str = "travel", crossed: Taught | None = None) -> None:
        super().__init__(run)
        self.goal = goal
        self.target = start
        self.side = 1 if goal >= start else -1
        self.velocity = 0.0
        self.kind = kind
        self.detector = ContactDetector(run, self.side)
        # (Where its own regime is as fast, what the model and free motion give it is the better feed-forward.)
        self.crossed = crossed if (crossed is not None and CROSSED[0] > run.travel_speed
                                   and crossed.covers(start, goal, 2 * run.leash)) else None
        self.top_speed, self.accel_limit = (CROSSED[0], accel_for(run.cap, run.inertia, CROSSED[1])) \
            if self.crossed is not None else (run.travel_speed, run.accel_limit)
        self.ramp = Ramp(self.accel_limit)
        self.budget_s = abs(goal - start) / run.speed + TIME_MARGIN_S
        self._leaving = leaving
        self._from: float | None = None
        self._t0: float | None = None
        self._reached: float | None = None

    def command(self) -> tuple[float, float]:
        return self.target, self.velocity

    def update(self, tick: Tick) -> None:
        run, s = self.run, self.side
        if self._t0 is None or self._from is None:
            self._t0, self._from = tick.t, tick.q
            self.detector.start(tick, self.target)
        if tick.t - self._t0 > self.budget_s:
            self.failure = f"did not reach {self.goal:+.3f} rad within {self.budget_s:.0f} s (at {tick.q:+.3f})"
            return
        if self._leaving and s * (tick.q - self._from) >= LIFT_RAD:
            self._leaving = False
            self.detector.start(tick, self.target)  # free of the stop: the baseline from here
        remaining = s * (self.goal - self.target)
        speed = self.ramp.step(tick.dt, min(self.top_speed, braking(0.0, remaining, self.accel_limit)))
        wanted = self.target + s * min(speed * tick.dt, max(remaining, 0.0))
        if self.crossed is not None and not self._leaving:  # what it needed here on the way across
            run.correction = self.crossed.correction(wanted)
        if self._leaving:
            most = s * tick.q + 2.0 * run.leash + run.weight / run.kp_leash  # it may have to lift its weight
            limited = wanted if s * wanted <= most else s * most
        else:
            limited = self.detector.leash(tick, wanted)
        free = limited == wanted
        if not free:
            self.ramp.held(s * (limited - self.target), tick.dt)
        self.velocity = s * self.ramp.speed if free and remaining > 0 else 0.0
        self.accel = s * self.ramp.accel if free else 0.0
        self.target = limited
        if self._leaving:
            if s * (self.target - tick.q) > 0.0:  # still on the stop: its weight is not in the feed-forward yet
                run.adapt(tick, self.target, most=2.0 * run.weight + run.cap)  # the model's gravity may be mirrored
            return
        if self._reached is None and s * (self.goal - self.target) <= 1e-9:
            self._reached = tick.t
        # Once the target rests at the goal nothing drives the joint further: what lag is left is its weight.
        if self._reached is None and self.detector.update(tick, self.target, free=free, speed=self.ramp.speed,
                                                          accel=self.ramp.accel):
            self.failure = f"touched something at {tick.q:+.3f} rad while moving to {self.goal:+.3f} rad"
            return
        if self._reached is not None:  # there, and stopped: measured, or given up on after ``SETTLE_TIMEOUT_S``
            run.adapt(tick, self.target)  # what lag is left is weight the feed-forward lacks: it takes it up
            settled = abs(tick.q - self.goal) < 0.25 * run.leash + 0.01 and abs(tick.qd) < 0.25 * run.speed
            self.finished = settled or tick.t - self._reached > SETTLE_TIMEOUT_S


class Approach(Segment):
    """Toward the stop ``search`` seeks, from the target ``start``, until contact where a stop can be (within the
    time budget); then press it with the leash until it is still, its position the stop, and with ``measure`` the
    effort at several depths and speeds."""

    def __init__(self, run: JointRun, search: Search, start: float, measure: bool) -> None:
        super().__init__(run)
        self.search = search
        self.side = search.side
        self.target = start
        self.velocity = 0.0
        self.measure = measure
        self.detector = ContactDetector(run, self.side)
        self.ramp = Ramp(run.accel_limit)
        spans = search.spans()
        self._spans = spans
        self._end = (spans[-1][1] if spans else 0.0) + run.leash  # the target goes no further
        self.budget_s = (search.seconds(run.travel_speed, run.search_speed) + 2 * len(spans) * run.travel_speed
                         / run.accel_limit + TIME_MARGIN_S)
        self.phase = "moving"  # then settling (its position recorded), easing and pushing (measured), done
        self.stop: float | None = None
        self.impact = 0.0  # the joint's speed when it met the stop (rad/s)
        self.points: list[tuple[float, float, float]] = []  # (lag, speed command, effort) into the stop, per tick
        self.peak = 0.0
        self._t0: float | None = None
        self._phase_t = 0.0
        self._still = Still()
        self._contact = 0.0  # where the contact was seen
        self._last: tuple[float, float] | None = None
        self.free: list[tuple[float, float]] = []  # (q, effort) in steady free motion, for the gravity fit
        self.taught = Taught(self.side)  # what the feed-forward learned along the way, to come back across it

    def command(self) -> tuple[float, float]:
        return self.target, self.velocity

    def limit(self, along: float) -> float:
        """The target's speed limit where it is (``along`` the search): the travel speed, braking to the contact
        speed before the next window, the contact speed within one, and none beyond the last. (Where the joint runs
        ahead of its target, ``_move`` holds the target back so that the joint meets a stop at the contact speed.)"""
        run = self.run
        for near, far in self._spans:
            if along < near - SLOW_LEAD_RAD:
                return min(run.travel_speed, braking(run.search_speed, near - SLOW_LEAD_RAD - along,
                                                     run.accel_limit))
            if along <= far:
                return run.search_speed
        return run.search_speed if along < self._end else 0.0

    def update(self, tick: Tick) -> None:
        if self._t0 is None:
            self._t0 = tick.t
            self.detector.start(tick, self.target)
        if tick.t - self._t0 > self.budget_s:
            self.failure = f"no stop on the {self._words()} side within {self.budget_s:.0f} s"
            return
        if self.phase == "moving":
            self._move(tick)
            self.kind = "travel" if self.ramp.speed > 1.05 * self.run.speed else "search"
            return
        run = self.run
        self.kind = "settle" if self.phase == "settling" else "push"
        self.peak = max(self.peak, self.detector.rise(tick))
        if self.phase == "settling":
            if self.side * (tick.q - self._contact) > YIELD_RAD:  # it went on under the press: that was no stop
                run.trace.contacts.pop()
                self.phase, self.impact, self.peak = "moving", 0.0, 0.0
                self._still = Still()
                self.detector.start(tick, self.target)
                return
            self._press(tick, DEPTH_RAMP[0], 0.0)
            if self._still.update(tick.q, tick.qd) or tick.t - self._phase_t >= SETTLE_TIMEOUT_S:
                self.stop = self._still.position if self._still.positions else tick.q
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

    def _move(self, tick: Tick) -> None:
        run, s, search = self.run, self.side, self.search
        along = search.along(self.target)
        limit = self.limit(along)
        most = GOVERN_SHARE * run.speed
        if limit <= run.search_speed and s * tick.qd > most:  # the joint runs ahead of its target: hold it back
            limit *= most / (s * tick.qd)
        was = self.ramp.speed
        speed = self.ramp.step(tick.dt, limit)
        wanted = self.target + s * speed * tick.dt
        limited = self.detector.leash(tick, wanted)
        free = limited == wanted
        if not free:
            self.ramp.held(s * (limited - self.target), tick.dt)
        self.velocity = s * self.ramp.speed if free else 0.0
        self.accel = s * self.ramp.accel if free else 0.0
        self.target = limited
        steady = free and self.ramp.accel == 0.0 and abs(s * tick.qd - speed) < 0.2 * speed
        if steady and speed >= 0.95 * run.travel_speed:  # one speed, one friction: the gravity fit's constant
            self.free.append((tick.q, tick.effort))
        if free and not self.detector.quiet(tick):
            self.taught.add(tick.q, run.correction)
        slowing = self.ramp.accel < 0.0 and was > 1.05 * run.speed  # from the travel speed
        if self.detector.update(tick, self.target, free=free, speed=self.ramp.speed, accel=-1.0 if slowing else 0.0):
            if not search.takes(tick.q):
                self.failure = (f"touched something at {tick.q:+.3f} rad, where no stop can be (moving toward its "
                                f"{self._words()} stop)")
                return
            self.impact = self.detector.impact
            self._contact = tick.q
            self.phase = "settling"
            self._phase_t = tick.t
            self.velocity = self.accel = 0.0
            run.trace.contacts.append((tick.t, tick.q))
            return
        if search.along(self.target) >= self._end - 1e-9 and abs(tick.qd) < 0.25 * run.speed:
            where = " or ".join(f"{min(a, b):+.2f} to {max(a, b):+.2f}" for a, b in search.windows)
            self.failure = f"no {self._words()} stop where it can be ({where} rad)"

    def _words(self) -> str:
        return "upper" if self.side > 0 else "lower"

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


class Taught:
    """What free motion taught a joint's feed-forward along its way (``JointRun.correction`` by position, the
    way it went): coming back across the same ground, the feed-forward it needed at each point, so it may go
    fast there (``CROSSED``). The friction it met turns with the motion, which the leash and what free motion
    teaches on the way back take up."""

    STEP_RAD = 0.01  # one value per this much of the way

    def __init__(self, side: int) -> None:
        self.side = side
        self.positions: list[float] = []
        self.values: list[float] = []

    def add(self, q: float, correction: float) -> None:
        if not self.positions or self.side * (q - self.positions[-1]) >= self.STEP_RAD:
            self.positions.append(q)
            self.values.append(correction)

    def covers(self, a: float, b: float, lead: float) -> bool:
        """Whether the way between targets ``a`` and ``b`` was crossed (within a step at either end, and the
        ``lead`` a target may have on the joint, pressing a stop the way ended at)."""
        if len(self.positions) < 2:
            return False
        low, high = sorted((self.positions[0], self.positions[-1]))
        slack = 2 * self.STEP_RAD + lead
        return all(low - slack <= x <= high + slack for x in (a, b))

    def correction(self, q: float) -> float:
        xs, ys = (self.positions, self.values) if self.side > 0 else (self.positions[::-1], self.values[::-1])
        return float(np.interp(q, xs, ys))


class JointRun:
    """The moving joint's settings and its per-tick command (loop thread). ``speed``: the contact speed;
    ``inertia``: the model's about its axis (kg m^2), which sets its acceleration and its feed-forward."""

    def __init__(self, index: int, name: str, *, cap: float, gains: tuple[float, float],
                 leash_gains: tuple[float, float], speed: float, rate: float, effort_limit: float,
                 inertia: float = 0.0, known: bool = False, found: bool = False) -> None:
        self.index = index
        self.name = name
        self.cap = cap
        self.kp, self.kd = gains
        kp_leash, kd_leash = leash_gains
        self.speed = speed
        self.search_speed = SEARCH_SHARE * speed  # the target's speed where a stop may be
        travel = TRAVEL[True] if known else FOUND if found else TRAVEL[False]
        self.travel_speed = max(travel[0], speed)
        self.rate = rate
        self.effort_limit = effort_limit
        self.kp_leash = kp_leash
        self.leash = (CAP_SHARE * cap - kd_leash * speed) / kp_leash
        self.inertia = inertia
        self.accel_limit = accel_for(cap, inertia, travel[1])
        self.trace = Trace()
        self.segment: Segment | None = None
        self.anchor = 0.0  # holding effort measured before moving
        self.gravity0 = 0.0  # the model's gravity torque there (host frame)
        self.correction = 0.0  # what free motion has taught the feed-forward (Nm)
        self.weight = 0.0  # the most gravity the model puts on the joint over its travel (Nm)
        self.bounds = (-math.inf, math.inf)  # where the target may go (the travel budget around the start)
        self.refused: str | None = None  # why the gate refused its command (None: it never did)
        self.seconds = dict.fromkeys(KINDS, 0.0)  # robot time by what it went to

    @property
    def active(self) -> bool:
        """Commanded by its own segment: not held the way the other joints are (before and after it moves)."""
        segment = self.segment
        return not (isinstance(segment, Hold) and segment.passive)

    def feed_forward(self, gravity: float) -> float:
        """The effort feed-forward (Nm, host frame) where the model puts ``gravity`` on the joint: the holding effort
        measured before it moved, the model's change of gravity since, what free motion taught it, what its
        target's acceleration asks of its inertia; within the joint's effort limit."""
        accel = self.segment.accel if self.segment is not None else 0.0
        ff = self.anchor + gravity - self.gravity0 + self.correction + self.inertia * accel
        return min(max(ff, -self.effort_limit), self.effort_limit)

    def adapt(self, tick: Tick, target: float, most: float | None = None) -> None:
        """In free motion, move the steady lag into the feed-forward: the model's gravity is only as good as the
        calibration it is evaluated with, which is what is being found (a flipped joint's is mirrored). Leaving a
        stop it rests on, the same takes up its weight, at most ``most``."""
        most = self.effort_limit if most is None else min(most, self.effort_limit)
        step = tick.dt / ADAPT_S * self.kp_leash * (target - tick.q)
        self.correction = min(max(self.correction + step, -most), most)

    @property
    def kind(self) -> str:
        """What this tick went to (``KINDS``)."""
        segment = self.segment
        return segment.kind if segment is not None else "settle"

    def count(self, dt: float) -> None:
        """This tick's time, by what the segment did."""
        self.seconds[self.kind] += dt
