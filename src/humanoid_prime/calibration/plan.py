"""Where a joint's stops can be, so that the hands-free calibration (``calibration.auto``) moves slowly only there
(DESIGN §5).

Positions are the run's host readings (the prior's direction, offset 0). A joint whose frame is not known turns
``relative`` to the prior's direction (+1 the same way, -1 the other) with some host offset ``c``:
``host = relative * angle + c``, where ``c`` is the prior's direction times its offset. Before it moves, what is
known is a set of ``Hypothesis``: per direction, an interval of offsets:

- a robot's prior calibration (a non-zero offset) puts each stop within ``PRIOR_WINDOW_RAD`` of where it says
  (``prior``); a recalibration searches there first, and only then where any offset allowed could put it;
- otherwise (the template's offset 0: a new robot) any direction, any offset within ``offset_range`` (``wide``);
- wherever the joint reads now, it is inside its range: offsets that would put it outside are dropped
  (``Hypothesis.holding``).

Each hypothesis puts a joint's stop on one side (+1: the larger host reading) in a window
(``Hypothesis.window``); a ``Search`` toward that side is the windows in the order the joint meets them, where it
moves at the contact speed, and the travel between them, at the travel speed. The first side is the one whose
windows cost the least time in the worst case (``first_side``). Once the first stop is found the other is the
described range away, within ``SPAN_TOLERANCE`` (``second``), and with a prior, near where the prior puts it first.

A stop met outside its windows but where some offset allowed could put it (``Search.plausible``) is still the
stop: the plan's assumption (the prior) was wrong, and the report says it was met at the travel speed. Met
anywhere else, it is something else, and the joint fails.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from humanoid_prime.config.robot import JointSpec

OFFSET_RANGE_RAD = 0.5  # default: a joint's offset lies within this of 0 when no calibration of the robot is known
PRIOR_WINDOW_RAD = 0.05  # a stop lies within this of where a robot's prior calibration puts it
STOP_MARGIN_RAD = 0.02  # each window is this much wider at each end (the description's limits, the readings)
SPAN_TOLERANCE = 0.05  # the stops' spacing is the described range within this share


@dataclass(frozen=True)
class Hypothesis:
    """The joint turns ``relative`` to the prior's direction with its host offset in [``low``, ``high``]."""

    relative: int
    low: float
    high: float

    def edge(self, spec: JointSpec, side: int) -> float:
        """The host reading of the stop on ``side`` at host offset 0."""
        ends = (self.relative * spec.lower, self.relative * spec.upper)
        return max(ends) if side > 0 else min(ends)

    def window(self, spec: JointSpec, side: int) -> tuple[float, float]:
        """Where its stop on ``side`` can be (host, lower reading first), with the margin."""
        edge = self.edge(spec, side)
        return edge + self.low - STOP_MARGIN_RAD, edge + self.high + STOP_MARGIN_RAD

    def holding(self, spec: JointSpec, reading: float) -> Hypothesis | None:
        """Narrowed to the offsets that put a joint reading ``reading`` within its range (None: none do)."""
        low = max(self.low, reading - self.edge(spec, 1) - STOP_MARGIN_RAD)
        high = min(self.high, reading - self.edge(spec, -1) + STOP_MARGIN_RAD)
        return Hypothesis(self.relative, low, high) if low <= high else None


def prior(direction: int, offset: float) -> list[Hypothesis]:
    """A robot's calibration (``direction``, ``offset``) as the run's prior: its own direction, its offset within
    ``PRIOR_WINDOW_RAD``."""
    c = direction * offset
    return [Hypothesis(1, c - PRIOR_WINDOW_RAD, c + PRIOR_WINDOW_RAD)]


def wide(offset_range: float) -> list[Hypothesis]:
    """Either direction, any offset within ``offset_range``."""
    return [Hypothesis(1, -offset_range, offset_range), Hypothesis(-1, -offset_range, offset_range)]


def holding(hypotheses: Sequence[Hypothesis], spec: JointSpec, reading: float) -> list[Hypothesis]:
    """Those of ``hypotheses`` that can hold a joint reading ``reading``, narrowed to it."""
    return [h for h in (h.holding(spec, reading) for h in hypotheses) if h is not None]


@dataclass(frozen=True)
class Search:
    """A stop sought toward ``side`` from ``start`` (host): ``windows`` (host, along the motion: each window's near
    end first) at the contact speed, in the order met, the travel speed between; ``plausible``: where a stop met is
    taken as the stop (lower reading first)."""

    side: int
    start: float
    windows: tuple[tuple[float, float], ...]
    plausible: tuple[tuple[float, float], ...]

    def along(self, position: float) -> float:
        """How far ``position`` is from the start along the motion (rad)."""
        return self.side * (position - self.start)

    def spans(self) -> list[tuple[float, float]]:
        """The windows as distances along the motion, (near, far)."""
        return [(self.along(a), self.along(b)) for a, b in self.windows]

    def takes(self, position: float) -> bool:
        """A stop met at ``position`` is plausible."""
        return any(low - STOP_MARGIN_RAD <= position <= high + STOP_MARGIN_RAD for low, high in self.plausible)

    def seconds(self, travel_speed: float, contact_speed: float) -> float:
        """The worst case: every window searched to its far end."""
        seconds, at = 0.0, 0.0
        for near, far in self.spans():
            seconds += max(near - at, 0.0) / travel_speed + (far - max(near, at)) / contact_speed
            at = far
        return seconds


def _merged(intervals: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    merged: list[tuple[float, float]] = []
    for low, high in sorted(intervals):
        if merged and low <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], high))
        else:
            merged.append((low, high))
    return merged


def _ahead(intervals: Sequence[tuple[float, float]], side: int, start: float) -> list[tuple[float, float]]:
    """The parts of ``intervals`` beyond ``start`` on ``side``, merged, in the order met from ``start``."""
    kept = [(max(low, start), high) if side > 0 else (low, min(high, start)) for low, high in intervals]
    kept = _merged([(low, high) for low, high in kept if low <= high])
    return kept if side > 0 else list(reversed(kept))


def _beyond(intervals: list[tuple[float, float]], first: list[tuple[float, float]], side: int
            ) -> list[tuple[float, float]]:
    """The parts of ``intervals`` (as ``_ahead`` gives them) beyond the last of ``first``."""
    if not first:
        return intervals
    return _ahead(intervals, side, first[-1][1] if side > 0 else first[-1][0])


def _oriented(intervals: Sequence[tuple[float, float]], side: int) -> tuple[tuple[float, float], ...]:
    """Intervals (lower reading first) as (near end, far end) along the motion."""
    return tuple((low, high) if side > 0 else (high, low) for low, high in intervals)


def joined(windows: Sequence[tuple[float, float]], extra: tuple[float, float], side: int
           ) -> tuple[tuple[float, float], ...]:
    """``windows`` (along a motion toward ``side``: near end first) with ``extra`` (near end first) among them,
    merged where they meet."""
    plain = [(min(a, b), max(a, b)) for a, b in (*windows, extra)]
    return _oriented(_merged(plain) if side > 0 else list(reversed(_merged(plain))), side)


def search(spec: JointSpec, side: int, start: float, slow: Sequence[Hypothesis],
           fallback: Sequence[Hypothesis] = ()) -> Search:
    """The search for the stop on ``side`` from ``start``: the windows of ``slow`` first, then those of
    ``fallback`` beyond them (a recalibration's prior, then any offset allowed); a stop is plausible in any."""
    windows = [h.window(spec, side) for h in slow], [h.window(spec, side) for h in fallback]
    first, others = _ahead(windows[0], side, start), _ahead(windows[1], side, start)
    # A stop is plausible anywhere a window puts it, behind the start too (a joint resting on it).
    return Search(side, start, _oriented(first + _beyond(others, first, side), side),
                  tuple(_merged(windows[0] + windows[1])))


def first_side(spec: JointSpec, start: float, slow: Sequence[Hypothesis], fallback: Sequence[Hypothesis],
               travel_speed: float, contact_speed: float) -> Search:
    """The search for the first stop: the side whose stop the joint may rest on where it is, else the side whose
    windows take the least time in the worst case; on a tie, the side whose first window is nearer."""
    candidates = [search(spec, side, start, slow, fallback) for side in (-1, 1)]
    resting = [c for c in candidates if c.takes(start)]
    if len(resting) == 1:  # it may rest on that stop: there first (the weight is the stop's until it lifts off)
        return resting[0]
    candidates = [c for c in candidates if c.windows] or candidates

    def cost(candidate: Search) -> tuple[float, float]:
        spans = candidate.spans()
        near = spans[0][0] if spans else math.inf
        return round(candidate.seconds(travel_speed, contact_speed), 3), near

    return min(candidates, key=cost)


def found(hypotheses: Sequence[Hypothesis], spec: JointSpec, side: int, stop: float) -> list[Hypothesis]:
    """Those of ``hypotheses`` whose stop on ``side`` could be at ``stop``, each narrowed to the offset it gives."""
    kept = []
    for h in hypotheses:
        low, high = h.window(spec, side)
        if low - STOP_MARGIN_RAD <= stop <= high + STOP_MARGIN_RAD:
            c = stop - h.edge(spec, side)
            kept.append(Hypothesis(h.relative, c, c))
    return kept


def second(spec: JointSpec, side: int, stop: float, at: float, prior_hypotheses: Sequence[Hypothesis] = ()
           ) -> Search:
    """The search for the stop on ``side`` from ``at`` once the other one is at ``stop``: the described range away
    within ``SPAN_TOLERANCE``, and with a prior whose window held the first stop, near where the prior puts the
    second first (then the rest of the range's window)."""
    span = spec.upper - spec.lower
    a, b = stop + side * span * (1 - SPAN_TOLERANCE), stop + side * span * (1 + SPAN_TOLERANCE)
    ranged = (min(a, b), max(a, b))
    near_prior = [h.window(spec, side) for h in prior_hypotheses if found([h], spec, -side, stop)]
    narrowed = [(max(low, ranged[0]), min(high, ranged[1])) for low, high in near_prior]
    narrowed = [(low, high) for low, high in narrowed if low <= high]
    first = _ahead(narrowed, side, at)
    return Search(side, at, _oriented(first + _beyond(_ahead([ranged], side, at), first, side), side), (ranged,))
