"""The loop's statistics: each tick's cost, the part of it spent in bus I/O, and the period between ticks."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import SupportsFloat

import numpy as np
import numpy.typing as npt


@dataclass
class LoopStats:
    """Tick cost (read + update + write, without the wait), the part of it spent in bus I/O (the hardware
    components' ``io_s``), and tick-to-tick period, in ring buffers."""

    period: float
    capacity: int = 1 << 16
    ticks: int = 0
    overruns: int = 0
    costs: npt.NDArray[np.float64] = field(init=False, repr=False)
    ios: npt.NDArray[np.float64] = field(init=False, repr=False)
    periods: npt.NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.costs = np.zeros(self.capacity)
        self.ios = np.zeros(self.capacity)
        self.periods = np.full(self.capacity, np.nan)
        # The tick writes through plain memoryviews of doubles: one C store each, not NumPy's item assignment.
        self._rows = tuple(a.data.cast("B").cast("d") for a in (self.costs, self.ios, self.periods))

    def record(self, cost: float, period: float, io: float = 0.0) -> None:
        """``period`` is NaN for the first tick."""
        i = self.ticks % self.capacity
        costs, ios, periods = self._rows
        costs[i] = cost
        ios[i] = io
        periods[i] = period
        self.ticks += 1

    def split_us(self) -> dict[str, dict[str, float | None]]:
        """The tick cost split in our CPU (cost minus bus I/O) and bus I/O: median, p99 and max of each."""
        k = min(self.ticks, self.capacity)
        if not k:
            empty = {"median": None, "p99": None, "max": None}
            return {"cpu": dict(empty), "io": dict(empty)}
        figures: dict[str, dict[str, float | None]] = {}
        for name, values in (("cpu", self.costs[:k] - self.ios[:k]), ("io", self.ios[:k])):
            median, p99, top = np.percentile(values, (50, 99, 100)) * 1e6
            figures[name] = {"median": round(float(median), 3), "p99": round(float(p99), 3),
                             "max": round(float(top), 3)}
        return figures

    def jitter_us(self, percentiles: tuple[float, ...]) -> dict[float, float]:
        """Percentiles of |period - nominal| in us over the last ``capacity`` ticks (empty before two ticks)."""
        k = min(self.ticks, self.capacity)
        periods = self.periods[:k]
        periods = periods[np.isfinite(periods)]
        if not periods.size:
            return {}
        values = np.percentile(np.abs(periods - self.period) * 1e6, percentiles)
        return {p: float(v) for p, v in zip(percentiles, values, strict=True)}

    def tick_us(self) -> dict[str, float | None]:
        """Tick cost median, p99 and max over the last ``capacity`` ticks, in one pass (the live table asks
        for these several times a second, from a thread that shares the interpreter with the loop)."""
        k = min(self.ticks, self.capacity)
        if not k:
            return {"median": None, "p99": None, "max": None}
        median, p99, top = np.percentile(self.costs[:k], (50, 99, 100)) * 1e6
        return {"median": round(float(median), 3), "p99": round(float(p99), 3), "max": round(float(top), 3)}

    def summary(self) -> dict[str, object]:
        """Figures over the last ``capacity`` ticks; None where there is nothing to measure yet."""
        k = min(self.ticks, self.capacity)
        periods = self.periods[:k]
        periods = periods[np.isfinite(periods)]
        jitter = self.jitter_us((99,))

        def stat(values: npt.NDArray[np.float64],
                 fn: Callable[[npt.NDArray[np.float64]], SupportsFloat]) -> float | None:
            return round(float(fn(values)), 3) if values.size else None

        return {
            "ticks": self.ticks,
            "overruns": self.overruns,
            "tick_us": self.tick_us(),
            **{f"tick_{part}_us": figures for part, figures in self.split_us().items()},
            "period_ms": {"mean": stat(periods * 1e3, np.mean)},
            "jitter_us": {"p99": round(jitter[99], 3) if jitter else None},
        }
