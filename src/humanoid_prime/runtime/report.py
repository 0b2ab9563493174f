"""What a run says of itself: the history of every flag (``FaultRecord``), what held when it ended (``RunEnd``, read
fresh from the buses), why it is not a success (``run_problems``) and its summary (``run_summary``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypedDict

import numpy as np

from humanoid_prime.control.flags import Level

if TYPE_CHECKING:
    from humanoid_prime.runtime.session import Session


@dataclass
class FaultRecord:
    """One problem of the run: what, how bad, when it appeared and when it cleared (None: it held to the end),
    in seconds since the run began."""

    key: str
    text: str
    level: Level
    since_s: float
    until_s: float | None = None

    def as_dict(self) -> dict[str, object]:
        return {"key": self.key, "level": self.level.name, "text": self.text, "since_s": round(self.since_s, 3),
                "until_s": None if self.until_s is None else round(self.until_s, 3)}


class RunEnd(TypedDict, total=False):
    """What held when the run ended (``read_end``); the EtherCAT and Sito parts where the run had them."""

    position: dict[str, float | None]  # the last tick's joint angles, rad (None: unknown)
    slaves: int
    slaves_op: int
    drives_enabled: int
    drives_faulted: list[str]
    sito: int
    sito_online: int


def read_end(session: Session) -> RunEnd:
    """What holds as ``session`` ends, read fresh from the buses before they close: slaves in OP, drives enabled
    or faulted, wrists heard from."""
    end: RunEnd = {"position": session.final_position}
    ethercat = session.ethercat
    if ethercat is not None and ethercat.master is not None:
        master = ethercat.master
        try:
            states = [s.al_state for s in master.read_states()]
        except Exception as exc:  # a dead ring is an answer too
            states = []
            session.record_fault("ethercat/end", f"AL states not readable at the end of the run: {exc}")
        end["slaves"] = len(master.slaves)
        end["slaves_op"] = sum(1 for state in states if state == 0x08)
        end["drives_enabled"] = int(np.count_nonzero(ethercat.enabled))
        end["drives_faulted"] = [ethercat.joints[k] for k in np.flatnonzero(ethercat.faulted)]
    if session.sito is not None:
        silent = {key.rsplit("/", 1)[-1] for key in session.sito.flags if "/rx_timeout/" in key}
        end["sito"] = len(session.robot.hardware.mit_joints)
        end["sito_online"] = end["sito"] - len(silent)
    return end


def run_problems(session: Session) -> list[str]:
    """Why the run of ``session`` is not a success, one line each (empty: every device did what it was asked)."""
    lines = [f"{r.key} at {r.since_s:.2f} s: {r.text}" for r in session.faults if r.level is Level.ERROR]
    end = session.end
    if end.get("slaves_op", 0) < end.get("slaves", 0):
        lines.append(f"{end['slaves'] - end['slaves_op']} of {end['slaves']} EtherCAT slaves not in OP at the end")
    if end.get("drives_faulted"):
        lines.append(f"drives in fault at the end: {', '.join(end['drives_faulted'])}")
    if end.get("sito_online", 0) < end.get("sito", 0):
        silent = end["sito"] - end["sito_online"]
        lines.append(f"{silent} of {end['sito']} Sito wrists silent at the end")
    for report in session.impedance.reports if session.impedance is not None else ():
        failed = report.as_dict()["failed"]
        if failed:
            where = ", ".join(f"{joint} ({error})" for joint, error in failed.items())
            lines.append(f"{report.mode} gains not applied on {where}")
    lines += [f"gate not reset: {failure}" for failure in session.gate_reset_failures]
    return lines


def run_summary(session: Session) -> dict[str, object]:
    """The report of the run of ``session``, as ``prime bringup --json`` prints it."""
    stats = session.manager.stats.summary()
    ec_bringup = None
    if session.ethercat is not None and session.ethercat.bringup is not None:
        ec_bringup = session.ethercat.bringup.as_dict()
        master = session.ethercat.master
        if master is not None:  # who worked the mailboxes, and what they dropped, by why
            ec_bringup.update(mailbox=master.mailbox, mailbox_drops=master.mailbox_drops(),
                              mailbox_given_up=master.mailbox_given_up())
        ec_bringup["rated_torque_nm"] = {  # 0x6076 of each drive; null: unread, nominal used
            joint: (float(r) if math.isfinite(r) else None)
            for joint, r in zip(session.ethercat.joints, session.ethercat.rated_torque_nm, strict=True)}
    problems = run_problems(session)
    return {
        "ok": not problems,
        "problems": problems,
        "backends": session.options.backends,
        "emulate": session.options.emulated,
        "config": session.manager.configuration,
        "update_rate": session.manager.update_rate,
        "bringup_seconds": session.bringup_seconds,
        "stages": [{"name": name, "seconds": seconds} for name, seconds in session.stages],
        "ethercat_bringup": ec_bringup,
        "end": dict(session.end),
        "mode_switches": [r.as_dict() for r in session.impedance.reports] if session.impedance is not None else [],
        "modes_visited": list(session.manager.modes_visited),
        "ticks": stats["ticks"],
        "tick_us": stats["tick_us"],
        "tick_cpu_us": stats["tick_cpu_us"],
        "tick_io_us": stats["tick_io_us"],
        "jitter_us": stats["jitter_us"],
        "overruns": stats["overruns"],
        "fallbacks": list(session.manager.fallbacks),
        "refused": session.manager.gate.refused.as_dict(),
        "faults": [r.as_dict() for r in session.faults],
        "gate_reset_failures": list(session.gate_reset_failures),
        **{key: value for key, value in session.reports.items()},
    }
