"""A mode switch asked for from outside the loop (``prime switch``, the control socket), followed to its end:
the mode active, refused, or fallen back, and on the eRob the new gains applied or not."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol, Required, TypedDict

from humanoid_prime.modes import Mode

if TYPE_CHECKING:  # `prime switch` imports this module for ``describe``: nothing heavy at import
    from humanoid_prime.control.manager import ControllerManager
    from humanoid_prime.runtime.gain_switch import SwitchReport, SwitchReportDict

GAINS_POLL_S = 0.01


class SwitchAnswer(TypedDict, total=False):
    """What became of a switch (``mode_switcher``), as the control socket answers it."""

    mode: Required[str]
    outcome: Required[str]  # requested, active, fell_back, superseded, gains_failed or pending
    active: str | None  # the mode active once the request was applied
    reason: str
    gains: SwitchReportDict  # the eRob's switch, when the run has an impedance manager


class _Reports(Protocol):
    reports: list[SwitchReport]  # in the order the switches were made


def mode_switcher(manager: ControllerManager, impedance: _Reports | None = None,
                  before: Callable[[], None] | None = None) -> Callable[[Mode, float], SwitchAnswer]:
    """``switch(mode, wait_s)``: request ``mode`` (``before`` runs first, e.g. the simulation hands the modes
    to the operator) and, unless ``wait_s`` is 0, wait up to that long for its outcome. The answer's
    ``outcome`` is ``requested`` (no wait), ``active``, ``fell_back``, ``superseded``, ``gains_failed`` or
    ``pending`` (not applied in time); a refused mode raises PrimeError."""

    def switch(mode: Mode, wait_s: float) -> SwitchAnswer:
        if before is not None:
            before()
        switches_before = len(impedance.reports) if impedance is not None else 0
        ticket = manager.request_mode(mode)
        if wait_s <= 0:
            return {"mode": mode.value, "outcome": "requested"}
        deadline = time.monotonic() + wait_s
        outcome = manager.wait_mode(ticket, wait_s)
        if outcome is None:
            return {"mode": mode.value, "outcome": "pending",
                    "reason": f"the control loop did not apply it within {wait_s:g} s"}
        active = outcome.active.value if outcome.active is not None else None
        if outcome.reason:
            kind = "superseded" if outcome.reason.startswith("superseded") else "fell_back"
            return {"mode": mode.value, "active": active, "outcome": kind, "reason": outcome.reason}
        if impedance is not None:
            report = _gains_report(impedance, switches_before, mode, deadline)
            if report is None:
                return {"mode": mode.value, "active": active, "outcome": "pending",
                        "reason": f"the eRob gains of {mode.value} were not reported applied within {wait_s:g} s"}
            gains = report.as_dict()
            if not report.ok:
                failed = ", ".join(f"{joint} ({error})" for joint, error in report.as_dict()["failed"].items())
                return {"mode": mode.value, "active": active, "gains": gains, "outcome": "gains_failed",
                        "reason": f"eRob gains not applied on {failed}"}
            return {"mode": mode.value, "active": active, "gains": gains, "outcome": "active"}
        return {"mode": mode.value, "active": active, "outcome": "active"}

    return switch


def _gains_report(impedance: _Reports, after: int, mode: Mode, deadline: float) -> SwitchReport | None:
    """The impedance manager's report of the switch to ``mode`` made after its ``after``-th, once it is there."""
    while True:
        for report in impedance.reports[after:]:
            if report.mode == mode.value:
                return report
        if time.monotonic() >= deadline:
            return None
        time.sleep(GAINS_POLL_S)


def describe(answer: SwitchAnswer) -> str:
    """One line for a person: what became of the switch."""
    mode, outcome = answer["mode"], answer["outcome"]
    if outcome == "requested":
        return f"requested {mode}"
    if outcome == "active":
        gains = answer.get("gains")
        if gains is None:
            return f"{mode} active"
        slaves = gains.get("slaves")
        count = f" on {len(slaves)} eRob" if isinstance(slaves, (list, dict)) else " on the eRob"
        return f"{mode} active; gains applied{count} in {gains['wall_seconds'] * 1e3:.1f} ms"
    return f"{mode} not active ({outcome.replace('_', ' ')}): {answer.get('reason', '')}"
