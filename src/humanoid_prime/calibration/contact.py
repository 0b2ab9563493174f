"""What the moving joint's measurements say, tick by tick (``calibration.approach`` uses them; DESIGN §5).

``ContactDetector`` keeps the free-motion baseline of the moving joint's lag and effort, holds its target to the
leash (the target never leads the joint by more than its baseline lag plus ``leash``), and sees contact: lag beyond
the baseline, no motion and a rise of effort, all together for ``DEBOUNCE_S``, never one sample. In free motion the
baselines follow slowly; at the travel speed, where the model's gravity (only as good as the calibration being
found) can be wrong by more than the leash over a second, they follow the lag as long as the joint keeps up with
its target, since an obstacle shows as the joint falling behind, not as a lag that moves with it.

``Still`` is measured rest: the joint slower than ``STILL_RAD_S`` and within ``STILL_SPREAD_RAD`` for
``STILL_TICKS`` ticks in a row, instead of a fixed wait.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from humanoid_prime.calibration.approach import JointRun

BASELINE_S = 0.1  # time constant of the free-motion baseline (lag and effort)
DEBOUNCE_S = 0.06  # contact is every sign for this long, never one sample
EXCESS_SHARE = 0.5  # contact: the lag beyond its baseline exceeds this share of the leash,
STALL_SHARE = 0.25  # the joint moves at less than this share of the contact speed,
EFFORT_SHARE = 0.25  # and its effort rose by this share of the cap
KEEP_UP_SHARE = 0.7  # at the travel speed, a joint moving at this share of its target's speed keeps up
STILL_RAD_S = 0.01  # a joint slower than this,
STILL_SPREAD_RAD = 5e-4  # and within this,
STILL_TICKS = 3  # for this many ticks in a row, is still
TRANSIENT_S = 0.3  # after the target slowed down, the joint catches up with it (or it with the joint) this long
IMPACT_TICKS = 3  # the speed a stop was met at: the fastest in this many ticks before the contact's first sign


@dataclass
class Tick:
    """One control tick of the moving joint: time, period, position, velocity, effort and its feed-forward."""

    t: float
    dt: float
    q: float
    qd: float
    effort: float
    ff: float


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
        self.speeds: deque[float] = deque(maxlen=self.needed + IMPACT_TICKS)
        self.impact = 0.0  # how fast the joint met what it touched (rad/s)
        self.stalled_at = 0.0  # how fast it was going when it stopped while its target slowed down (0: it did not)
        self.quiet_until = -math.inf  # no contact counts before (the target's speed changed)

    def start(self, tick: Tick, target: float) -> None:
        s = self.side
        self.lag_base = s * (target - tick.q)
        self.effort_base = s * (tick.effort - tick.ff)
        self.stalled_at = 0.0

    def leash(self, tick: Tick, wanted: float) -> float:
        """``wanted``, held back so the target leads the joint by at most its baseline lag plus the leash."""
        s = self.side
        most = s * tick.q + self.lag_base + self.run.leash
        return wanted if s * wanted <= most else s * most

    def update(self, tick: Tick, target: float, *, free: bool, speed: float = 0.0, accel: float = 0.0) -> bool:
        """Take this tick's measurements (``speed``, ``accel``: the target's, along the motion; ``accel`` negative only
        where it slows down from the travel speed); True once contact has held for the debounce time. While the
        target slows down, and for ``TRANSIENT_S`` after, nothing counts
        and the baselines follow: the joint overshoots its target by what the model's gravity and inertia got wrong
        (the plan slows down where no stop can be, ``approach.SLOW_LEAD_RAD`` before a window)."""
        run, s = self.run, self.side
        lag = s * (target - tick.q)
        effort = s * (tick.effort - tick.ff)
        self.speeds.append(abs(tick.qd))
        alpha = min(1.0, tick.dt / BASELINE_S)
        if accel < 0.0:
            self.quiet_until = tick.t + TRANSIENT_S
        if tick.t < self.quiet_until:  # the target slowed down: the baselines follow, nothing counts
            if s * tick.qd > STALL_SHARE * run.speed:  # (but a joint that stopped is not catching up: what
                self.lag_base += alpha * (lag - self.lag_base)  # stopped it shows once the quiet ends, and how
                self.effort_base += alpha * (effort - self.effort_base)  # fast it was going then is kept)
                self.stalled_at = 0.0
            elif self.stalled_at == 0.0:
                self.stalled_at = max(self.speeds)
            self.count = 0
            return False
        if s * tick.qd > STALL_SHARE * run.speed:  # moving on: whatever stopped it before did not hold it
            self.stalled_at = 0.0
        excess = lag - self.lag_base
        rise = effort - self.effort_base
        keeping_up = speed > 1.5 * run.speed and s * tick.qd >= KEEP_UP_SHARE * speed
        if free and (excess < 0.5 * EXCESS_SHARE * run.leash or keeping_up):
            self.lag_base += alpha * (lag - self.lag_base)
            self.effort_base += alpha * (effort - self.effort_base)
            run.adapt(tick, target)
        touching = (excess >= EXCESS_SHARE * run.leash and s * tick.qd <= STALL_SHARE * run.speed
                    and rise >= EFFORT_SHARE * run.cap)
        self.count = self.count + 1 if touching else 0
        if self.count >= self.needed:
            self.impact = max(max(list(self.speeds)[:IMPACT_TICKS]), self.stalled_at)
            return True
        return False

    def quiet(self, tick: Tick) -> bool:
        """Whether the joint is catching up with a target that slowed down (nothing counts)."""
        return tick.t < self.quiet_until

    def rise(self, tick: Tick) -> float:
        return self.side * (tick.effort - tick.ff) - self.effort_base


class Still:
    """Measured rest: ``update`` is True once the joint has been still for ``STILL_TICKS`` ticks in a row;
    ``position`` is its mean over them."""

    def __init__(self) -> None:
        self.positions: deque[float] = deque(maxlen=STILL_TICKS)

    def update(self, q: float, qd: float) -> bool:
        if abs(qd) > STILL_RAD_S:
            self.positions.clear()
            return False
        self.positions.append(q)
        if len(self.positions) == STILL_TICKS and max(self.positions) - min(self.positions) > STILL_SPREAD_RAD:
            self.positions.popleft()
        return len(self.positions) == STILL_TICKS

    @property
    def position(self) -> float:
        return sum(self.positions) / len(self.positions)
