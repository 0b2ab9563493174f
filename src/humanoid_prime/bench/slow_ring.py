"""Bring-ups against a slow virtual Prime: is each one fully up, or does it fail saying what happened?

Each run is a whole ``prime bringup --emulate`` in this process (in its private network namespace) with a
STANDBY, DAMPING, STANDBY sequence, against a virtual Prime whose eRob answer the way a busy drive or host makes
them: mailbox replies late at random and in bursts, the frames that carry replies back after the 2 ms SOEM gives a
frame (two of them scripted into each bring-up's PDO mapping), and the emulator stalling now and then. A run is:

- ``up``: every slave reached OP, every switch's gains were written, the slaves confirmed in OP after it and the
  gains read back as written, and no slave left OP during the run (nothing knocked a drive out);
- ``failed``: the bring-up or a switch did not succeed; its message is kept, to be read for whether it says what
  really happened (a late reply is not a refused mapping, a slow slave is not a power cycle).

``python -m humanoid_prime.bench.slow_ring --runs 50 [--quirks all] [--output FILE]`` (root, or in ``unshare -rn``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, TypedDict

from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode

if TYPE_CHECKING:  # the virtual Prime is imported when a run starts it
    from humanoid_prime.virtual.ring.options import RingSettings

SEQUENCE = (Mode.STANDBY, Mode.DAMPING, Mode.STANDBY)
# How slow: a reply takes 0.5 ms plus up to 4 ms at random, 1 in 50 starts a burst of 5 replies each 30 ms late,
# and about every 2 s the emulator stalls for 25 ms (every frame, the cycle's too, waits that long).
SLOW: RingSettings = {"mailbox_latency_s": 0.0005, "mailbox_jitter_s": 0.004, "mailbox_burst_s": 0.030,
        "mailbox_burst_chance": 0.02, "mailbox_burst_replies": 5, "stall_interval_s": 2.0, "stall_s": 0.025}
HELD_REPLY_FRAMES = 2  # reply frames held back 8 ms during each bring-up's mapping
HELD_S = 0.008


class Switch(TypedDict):
    """A mode switch of a run, as the impedance manager reported it."""

    mode: str
    ok: bool
    wall_ms: float
    retries: int
    failed: dict[str, str]  # joint -> its problem


class LateReply(TypedDict):
    ring: int
    what: str
    late_ms: float


class SlowRun(TypedDict, total=False):
    """One bring-up's verdict ("up" or "failed", with the stage and message) and what it saw."""

    seed: int
    verdict: str
    stage: str  # where it failed: "bring-up" or "run"
    message: str
    seconds: float
    configured_again: list[str]  # why the ring was scanned or configured again
    left_op: list[int]  # per slave, how often it left OP
    al_status_codes: list[str]
    flags: list[tuple[float, str, str]]  # (since s, key, text)
    loop_ended_s: float
    switches: list[Switch]
    late_replies: int
    mailbox_drops: dict[str, int]  # by why
    late_mailbox_replies: list[LateReply]
    emulator: dict[str, int]  # its stalls, held reply frames and slow replies


def one_run(seed: int, *, dwell_s: float = 2.0, quirks: str = "") -> SlowRun:
    """One bring-up with the sequence against a slow virtual Prime (its slaves with ``quirks``, as
    virtual/ring/quirks.py names them); its verdict and what it saw."""
    from humanoid_prime.drivers.ethercat.soem_master import SoemMaster
    from humanoid_prime.runtime.run import run_loop
    from humanoid_prime.runtime.session import BringupOptions, open_session, plan_session
    from humanoid_prime.virtual.harness import attach_virtual_prime

    options = BringupOptions(emulated=True, sequence=SEQUENCE, dwell=dwell_s, realtime=True, control_socket=None)
    began = time.monotonic()
    result: SlowRun = {"seed": seed}
    with contextlib.ExitStack() as stack:
        plan = plan_session(options)
        virtual = attach_virtual_prime(stack, ring_options={**SLOW, "seed": seed, "quirks": quirks})
        virtual.wire_into(options)
        virtual.control.hold_reply_frames(HELD_REPLY_FRAMES, HELD_S)
        try:
            session = open_session(plan, stack)
        except PrimeError as exc:
            result.update({"verdict": "failed", "stage": "bring-up", "message": str(exc),
                           "seconds": time.monotonic() - began})
            return result
        master = session.ethercat.master if session.ethercat is not None else None
        impedance = session.impedance
        if not isinstance(master, SoemMaster) or impedance is None:
            raise PrimeError("the emulated bring-up has no SOEM master or no impedance manager on its ring")
        result["configured_again"] = [*master.scan_reasons, *master.configure_reasons]
        run_loop(session, threading.Event())
        left_op = result["left_op"] = [int(n) for n in master.left_op]  # the run's own, before anything winds
        # down
        result["al_status_codes"] = [f"0x{int(c):04X}" for c in master.al_status_code]
        result["flags"] = [(round(r.since_s, 2), r.key.split("/", 1)[-1], r.text[:160]) for r in session.faults
                           if r.key.endswith("/lost") or "ring" not in r.key][:12]
        result["loop_ended_s"] = round(time.monotonic() - plan.began, 2)
        problems = list(session.problems)
        impedance.wait_checked(10.0)
        switches = [r.as_dict() for r in impedance.reports]
        result["switches"] = [{"mode": s["mode"], "ok": s["ok"], "wall_ms": round(s["wall_seconds"] * 1e3, 1),
                               "retries": s["retries"], "failed": s["failed"]} for s in switches]
        result["late_replies"] = len(master.late_replies())
        result["mailbox_drops"] = master.mailbox_drops()
        # each reply counted late with the request it answered and how long after it was sent: never one that
        # answered no earlier request (those are counted as for another object, unrecognised or malformed)
        result["late_mailbox_replies"] = [
            {"ring": r.position, "what": r.what, "late_ms": round((r.late_s or 0.0) * 1e3, 1)}
            for r in list(master.drops.records) if r.reason == "late"]
        stats = virtual.control.stats()
        result["emulator"] = {"stalls": stats["stalls"], "held_reply_frames": stats["held_reply_frames"],
                              "slow_replies": stats["slow_replies"]}
        modes = [s["mode"] for s in switches]
        problems += [f"{s['mode']}: {s['failed']}" for s in switches if not s["ok"]]
        if modes[-len(SEQUENCE):] != [m.value for m in SEQUENCE]:
            problems.append(f"switches {modes}, expected {[m.value for m in SEQUENCE]}")
        if any(left_op):
            problems.append(f"slaves left OP: {left_op}")
    result["seconds"] = time.monotonic() - began
    result["verdict"] = "up" if not problems else "failed"
    if problems:
        result.update({"stage": "run", "message": "; ".join(problems)})
    return result


def bench_slow_ring(runs: int = 50, *, quirks: str = "", report: Callable[[str], None] = print) -> dict[str, object]:
    results: list[SlowRun] = []
    for k in range(runs):
        result = one_run(seed=k, quirks=quirks)
        results.append(result)
        line = f"run {k + 1}/{runs}: {result['verdict']} in {result['seconds']:.1f} s"
        if result.get("configured_again"):
            line += f"; configured again: {result['configured_again']}"
        if "mailbox_drops" in result:
            line += f"; mailbox messages dropped {result['mailbox_drops']}, frames late {result['late_replies']}"
        if result["verdict"] != "up":
            line += f"; {result['stage']}: {result['message']}"
        report(line)
    up = sum(1 for r in results if r["verdict"] == "up")
    return {"runs": runs, "up": up, "failed": runs - up, "slow": SLOW, "quirks": quirks,
            "held_reply_frames_per_bringup": HELD_REPLY_FRAMES, "held_s": HELD_S,
            "knocked_out_of_op": sum(1 for r in results if any(r.get("left_op", ()))), "results": results}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m humanoid_prime.bench.slow_ring",
                                     description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--output", metavar="FILE")
    parser.add_argument("--quirks", default="", help="quirk profiles of the slaves, comma-separated, or all")
    args = parser.parse_args(argv)
    from humanoid_prime.virtual.harness import enter_private_netns

    enter_private_netns()
    figures = bench_slow_ring(args.runs, quirks=args.quirks)
    print(f"{figures['up']} of {figures['runs']} bring-ups fully up; slaves knocked out of OP in "
          f"{figures['knocked_out_of_op']} runs")
    if args.output:
        with open(args.output, "w") as out:
            json.dump(figures, out, indent=1)
    return 0 if figures["up"] == figures["runs"] else 1


if __name__ == "__main__":
    sys.exit(main())
