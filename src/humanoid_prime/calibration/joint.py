"""One joint's part of a hands-free calibration (``calibration.auto`` runs it, beside the other arm's): the joint
set up to move (``moving``), its stops found along the plan (``find_stops``, ``calibration.plan``) and what they
say (``conclude``). Each is a procedure for ``calibration.sequence``: it yields what it waits for.

``moving`` anchors the joint where it is (its holding effort measured while it is still), puts an eRob on a ring
on its approach drive settings (``calibration.drive``, recorded in the run's journal first), runs the work, and
afterwards holds the joint where it ended, on the impedance it had; a joint the gate refused goes back to where it
started first. ``find_stops`` goes to the first stop the plan chooses, backs off, goes to the other (at the
travel speed where neither can be) and back to where it started.

A joint whose frame is not known (a new robot) does that in two parts (``calibration.auto`` runs the first part of
every such joint before the second of any): ``first_stop`` goes to its first stop at the contact speed and back
across what it crossed (``approach.CROSSED``), which tells its offset (``FirstStop``, up to its direction where the
range cannot tell it); ``calibrate`` then goes to the other stop from there, at the travel speed where no stop can
be and the body check under every direction still possible clears it.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from humanoid_prime.calibration import plan
from humanoid_prime.calibration.approach import Approach, Hold, JointRun, Move, approach_gains
from humanoid_prime.calibration.direction import direction_from_limits
from humanoid_prime.calibration.drive import approach_drive
from humanoid_prime.calibration.report import fit_stiffness
from humanoid_prime.calibration.sequence import Aborted, JointFailed, Steps, Until, Wait
from humanoid_prime.config.calibration import JointCalibration
from humanoid_prime.drivers.erob.gains import gains_to_registers, registers_to_gains
from humanoid_prime.errors import PrimeError

if TYPE_CHECKING:
    from humanoid_prime.calibration.auto import AutoCalibration

BACKOFF_RAD = 0.15  # a joint goes this far off a stop before it goes on: its weight may need the leash's whole lead
RESTING_RAD = 0.02  # a stop found this close to where the joint started: it rested on it
TRAVEL_MARGIN_RAD = 0.1  # beyond the joint's range (plus its tolerance), the most the target travels from its start

Floats = npt.NDArray[np.float64]


@dataclass
class FirstStop:
    """What a joint's first stop told: the approach that met it (``stop``, its peak and speed), the side, where it
    started and went back to, and the plan's hypotheses narrowed to the offsets that stop gives (one per direction
    still possible)."""

    approach: Approach
    side: int
    start: float
    found: list[plan.Hypothesis]
    slow: list[plan.Hypothesis]
    fallback: list[plan.Hypothesis]


@dataclass
class Sweep:
    """What a joint's stops and its sweep between them left for its direction: the calibration either way, the
    limits' verdict, where every joint was meanwhile (host frame) and (position, effort) in free motion."""

    same: JointCalibration
    flipped: JointCalibration
    by_limits: int | None
    config: Floats
    samples: Floats
    where_prior: bool = False  # both stops where a robot's prior calibration put them


def new_run(auto: AutoCalibration, joint: str) -> JointRun:
    """``joint``'s run: its cap, its approach gains (an eRob on a ring: what its registers give), its inertia, and
    how fast it travels: a robot's prior gives its frame, its first stop found it, or neither."""
    robot = auto.robot
    i = robot.index(joint)
    spec = robot.joints[i]
    cap = auto.caps[joint]
    gains = approach_gains(cap)
    leash_gains = gains
    if joint in auto.rings:
        hw = robot.hardware
        registers = gains_to_registers(*gains, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint],
                                       efficiency=hw.erob_torque_efficiency[joint])
        # The leash assumes the most stiffness the registers can give (a drive realises at most its nominal).
        leash_gains = registers_to_gains(registers, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint])
    state = auto.manager.resources.state
    # It travels fast where its frame is known and its arm's other eRob joints hold on their drives' own gains (an
    # arm held per tick, on the standby gains, gives way to what a fast motion of one of its joints asks).
    arm = joint.split("_", 1)[0] + "_"
    holding = [j for j in robot.names if j.startswith(arm) and j in robot.hardware.erob_joints and j != joint]
    stiff = all(j in auto.rings for j in holding)
    run = JointRun(i, joint, cap=cap, gains=gains, leash_gains=leash_gains, speed=auto.speed,
                   rate=auto.manager.update_rate, effort_limit=spec.effort_limit,
                   inertia=auto.model.inertia(auto.description_angles(state.position))[i],
                   known=auto.robots_prior[joint] and stiff,
                   found=joint in auto.firsts and joint in auto.clear and stiff)
    if run.leash <= 0:
        raise JointFailed(f"the speed {auto.speed:g} rad/s leaves no leash under the cap of {cap:g} Nm")
    run.trace = auto.traces.setdefault(joint, run.trace)  # the question's motion goes on the same trace
    start = float(state.position[i])
    budget = (spec.upper - spec.lower) * (1 + plan.SPAN_TOLERANCE) + TRAVEL_MARGIN_RAD
    run.bounds = (start - budget, start + budget)
    q = state.position.copy()
    reach = []  # the model's gravity on the joint over its travel: how heavy it can be
    for value in np.linspace(*run.bounds, 17):
        q[i] = value
        reach.append(abs(float(auto.host_gravity(q, auto.model)[i])))
    run.weight = max(reach)
    return run


def moving(auto: AutoCalibration, joint: str, work: Callable[[JointRun], Steps]) -> Steps:
    """``work`` with ``joint`` anchored where it is, on its approach impedance; afterwards held where it ended on
    the impedance it had (module docstring)."""
    controller, state = auto.controller, auto.manager.resources.state
    run = new_run(auto, joint)
    i = run.index
    start = float(state.position[i])
    controller.runs = (*controller.runs, run)
    try:
        hold = Hold(run, start, passive=True)
        run.gravity0 = float(auto.host_gravity(state.position, auto.model)[i])
        yield hold
        run.anchor = float(np.mean(hold.efforts))
        run.gravity0 = float(auto.host_gravity(state.position, auto.model)[i])
        ring = auto.rings.get(joint)
        drive: contextlib.AbstractContextManager[str] = contextlib.nullcontext("")
        if ring is not None:
            hw = auto.robot.hardware
            registers = gains_to_registers(run.kp, run.kd, kt=hw.erob_kt[joint], gear=hw.erob_gear[joint],
                                           efficiency=hw.erob_torque_efficiency[joint])
            drive = approach_drive(auto.robot, joint, run, registers, ring, journal=auto.journal)
        with drive as torque_limit:
            auto.outcomes[joint].drive_torque_limit = torque_limit
            try:
                yield from work(run)
            finally:  # however it ended: held where it is, with the effort it applies, before the gains go
                if auto.aborted is None and run.refused is not None:
                    auto.report(f"{joint}: the gate refused its command ({run.refused}); back to where it started")
                    yield Move(run, start, float(state.position[i]))
                if auto.aborted is None:
                    yield Hold(run)
    finally:
        controller.capture.add(i)  # held from here where it ended, with the effort it applies there
        with contextlib.suppress(Aborted):  # (a controller that lost the commands takes nothing)
            yield Until(lambda: i not in controller.capture or auto.manager.active is not controller,
                        abortable=False)
        if i in controller.capture:  # no tick came: take it here
            controller.capture.discard(i)
            controller.hold[i], controller.hold_effort[i] = float(state.position[i]), float(state.effort[i])
        controller.runs = tuple(r for r in controller.runs if r is not run)


def attempt(auto: AutoCalibration, joint: str, work: Callable[[JointRun], Steps]) -> Generator[Wait, None, bool]:
    """``work`` on ``joint`` (``moving``), its time added to the joint's: True once it ended; else a failure fails
    the joint, and an abort or a drive setting that could not be made or restored stops the run."""
    outcome = auto.outcomes[joint]
    state = auto.manager.resources.state
    began = state.stamp
    runs: list[JointRun] = []

    def counted(run: JointRun) -> Steps:
        runs.append(run)
        yield from work(run)

    try:
        yield from moving(auto, joint, counted)
        return True
    except JointFailed as exc:
        outcome.status, outcome.message = "failed", str(exc)
    except Aborted as exc:
        outcome.status, outcome.message = "aborted", str(exc)
    except PrimeError as exc:  # a drive setting that could not be made or restored: nothing more moves
        outcome.status, outcome.message = "aborted", str(exc)
        auto.abort(str(exc))
    finally:
        outcome.seconds += state.stamp - began
        for run in runs:
            for kind, seconds in run.seconds.items():
                outcome.times[kind] = outcome.times.get(kind, 0.0) + seconds
    return False


def calibrate(auto: AutoCalibration, joint: str) -> Steps:
    """``joint``'s stops (the other one, where its first is found), what they say, and its outcome, whatever
    happens (``attempt``)."""
    outcome = auto.outcomes[joint]

    def work(run: JointRun) -> Steps:
        first = auto.firsts.get(joint)
        yield from (find_stops(auto, run) if first is None else other_stop(auto, run, first))

    if (yield from attempt(auto, joint, work)) and outcome.calibration is not None:
        # The joint has stopped: the loop's model may take it now.
        auto.know(auto.robot.index(joint), outcome.calibration, settled=auto.sweeps[joint].by_limits is not None)
    if outcome.status == "direction_unknown":  # measured; its direction is settled at the end
        low, high = outcome.stops or (math.nan, math.nan)
        auto.report(f"{joint}: stops {high - low:.3f} rad apart in {outcome.seconds:.1f} s; its direction is "
                    "settled at the end")
    else:
        auto.report(f"{joint}: {outcome.status}" + (f" ({outcome.message})" if outcome.message else ""))


def first_stop(auto: AutoCalibration, joint: str) -> Steps:
    """A new robot's joint to its first stop at the contact speed and back across what it crossed: its
    ``FirstStop`` in ``auto.firsts``, and the offset it gives for the loop's model; its outcome as ``attempt``
    gives it."""
    outcome = auto.outcomes[joint]
    state = auto.manager.resources.state

    def work(run: JointRun) -> Steps:
        i = run.index
        start = float(state.position[i])
        a, first, slow, fallback = yield from approach_first(auto, run)
        auto.report(f"{joint}: stop at {a.stop:+.4f} rad; back across what it crossed")
        assert a.stop is not None
        # Back to where it started, or off the stop it rested on there.
        goal = start if first * (a.stop - start) > BACKOFF_RAD else a.stop - first * BACKOFF_RAD
        yield Move(run, goal, a.unloaded(float(state.position[i])), leaving=True, crossed=a.taught)
        spec = auto.robot.joints[i]
        found = plan.found(slow + fallback, spec, first, a.stop)
        auto.firsts[joint] = FirstStop(a, first, goal, found, slow, fallback)
        auto.assume(i, found)

    yield from attempt(auto, joint, work)
    if outcome.status != "not_reached":
        auto.report(f"{joint}: {outcome.status}" + (f" ({outcome.message})" if outcome.message else ""))


def approach_first(auto: AutoCalibration, run: JointRun
                   ) -> Generator[Wait, None, tuple[Approach, int, list[plan.Hypothesis], list[plan.Hypothesis]]]:
    """To the stop the plan chooses first, pressing it (again from off it, where the joint rested on it):
    the approach, its side and the plan's hypotheses (searched first, then)."""
    joint, i = run.name, run.index
    spec = auto.robot.joints[i]
    position = auto.manager.resources.state.position
    start = float(position[i])
    slow, fallback = auto.hypotheses(joint, start)
    if not slow and not fallback:
        raise JointFailed(f"it reads {start:+.3f} rad, which no offset within {auto.offset_range:g} rad puts inside "
                          "its range (give a larger --offset-range, or calibrate it by hand)")
    search = plan.first_side(spec, start, slow, fallback, run.travel_speed, run.speed)
    first = search.side
    auto.report(f"{joint}: toward its {'upper' if first > 0 else 'lower'} stop (at most {run.cap:.2f} Nm into it)")
    a = Approach(run, search, start, auto.measure)
    yield a
    assert a.stop is not None
    if abs(a.stop - start) < plan.STOP_MARGIN_RAD + RESTING_RAD:
        # It rested on that stop: its weight there was the stop's, not in its feed-forward. Off the stop (where free
        # motion teaches the feed-forward what gravity asks) and onto it again.
        auto.report(f"{joint}: it rested on that stop; again, from {BACKOFF_RAD:g} rad off it")
        off = Move(run, a.stop - first * BACKOFF_RAD, a.unloaded(float(position[i])), leaving=True)
        yield off
        near = (a.stop - RESTING_RAD, a.stop + RESTING_RAD)
        a = Approach(run, plan.Search(first, off.target, ((near[0], near[1]) if first > 0 else (near[1], near[0]),),
                                      (near,)), off.target, auto.measure)
        yield a
    assert a.stop is not None
    if a.impact > run.speed:  # met where the plan put no stop: the prior calibration is wrong here
        warning = (f"it met its {'upper' if first > 0 else 'lower'} stop at {a.impact:.2f} rad/s, faster than the "
                   f"contact speed, at {a.stop:+.3f} rad, where the prior calibration put none: that calibration "
                   "is wrong for this joint (calibrate a rebuilt joint from the bundled calibration)")
        auto.outcomes[joint].warnings.append(warning)
        auto.report(f"{joint}: {warning}")
    return a, first, slow, fallback


def find_stops(auto: AutoCalibration, run: JointRun) -> Steps:
    """The first stop the plan chooses, the other, and back to where it started; then ``conclude``."""
    joint, i = run.name, run.index
    spec = auto.robot.joints[i]
    position = auto.manager.resources.state.position
    start = float(position[i])
    a, first, slow, fallback = yield from approach_first(auto, run)
    assert a.stop is not None
    auto.report(f"{joint}: stop at {a.stop:+.4f} rad; now the other one")
    backed = Move(run, a.stop - first * BACKOFF_RAD, a.unloaded(float(position[i])), leaving=True,
                  crossed=a.taught)
    yield backed
    b = Approach(run, plan.second(spec, -first, a.stop, backed.target, slow if fallback else ()), backed.target,
                 auto.measure)
    yield from finish(auto, run, start, a, first, b)


def other_stop(auto: AutoCalibration, run: JointRun, first: FirstStop) -> Steps:
    """A new robot's joint, its first stop found: to the other from where it is, and back; then ``conclude``."""
    i = run.index
    spec = auto.robot.joints[i]
    position = auto.manager.resources.state.position
    start = float(position[i])
    a = first.approach
    assert a.stop is not None
    auto.report(f"{run.name}: to its {'upper' if first.side < 0 else 'lower'} stop, its first at {a.stop:+.4f} rad")
    search = plan.second(spec, -first.side, a.stop, start, first.slow if first.fallback else ())
    clear = auto.clear.get(run.name)
    if clear is not None and search.windows:  # beyond where the body check clears it: at the contact speed too
        s = search.side
        end = search.windows[-1][1]
        if s * (end - clear) > 0:
            search = plan.Search(s, start, plan.joined(search.windows, (clear, end), s), search.plausible)
    b = Approach(run, search, start, auto.measure)
    yield from finish(auto, run, first.start, a, first.side, b)


def finish(auto: AutoCalibration, run: JointRun, start: float, a: Approach, first: int, b: Approach) -> Steps:
    """The second stop's approach ``b``, back to where the joint started, and ``conclude``."""
    joint, i = run.name, run.index
    position = auto.manager.resources.state.position
    yield b
    assert a.stop is not None and b.stop is not None
    # Back to where it started, or off the stop it rested on there.
    low, high = sorted((a.stop, b.stop))
    auto.report(f"{joint}: stop at {b.stop:+.4f} rad; back to where it started")
    yield Move(run, min(max(start, low + BACKOFF_RAD), high - BACKOFF_RAD), b.unloaded(float(position[i])),
               leaving=True)
    outcome = auto.outcomes[joint]
    outcome.peak_contact_nm = max(a.peak, b.peak)
    outcome.impact_rad_s = max(a.impact, b.impact)
    outcome.first_side = first
    conclude(auto, run, a, b)


def conclude(auto: AutoCalibration, run: JointRun, a: Approach, b: Approach) -> None:
    """What the two stops say: the span checked against the described range, the calibration either way and the
    limits' verdict on the direction (settled at the end, with gravity)."""
    joint = run.name
    robot, outcome = auto.robot, auto.outcomes[joint]
    spec = robot.joints[run.index]
    assert a.stop is not None and b.stop is not None  # both approaches ended pressing their stops
    low, high = sorted((a.stop, b.stop))
    outcome.stops = (low, high)
    outcome.stiffness = fit_stiffness(robot, joint, joint in auto.rings, (run.kp, run.kd), [a.points, b.points])
    span, described = high - low, spec.upper - spec.lower
    if abs(span - described) > plan.SPAN_TOLERANCE * described:
        outcome.status = "failed"
        outcome.message = (f"the stops are {span:.3f} rad apart, the description says {described:.3f}: something "
                           "stopped the joint short of a stop, or this is not the joint the file says")
        return
    same, flipped, by_limits = direction_from_limits(int(auto.prior_direction[run.index]), (low, high), spec)
    # The direction is settled at the end, proximal first, when every other joint's calibration is known and the
    # model's gravity along this sweep can be trusted; meanwhile the limits' verdict, or the prior's.
    outcome.status = "direction_unknown"
    outcome.calibration = flipped if by_limits == -1 else same
    prior = auto.prior.joints[joint]
    # (A robot's calibration: a simulation's frame is known, but its template is no one's calibration of a joint.)
    windows = plan.prior(prior.direction, prior.homing_offset) if prior.homing_offset != 0.0 else []
    where_prior = bool(windows) and all(plan.found(windows, spec, side, stop) for side, stop in ((-1, low), (1, high)))
    auto.sweeps[joint] = Sweep(same, flipped, by_limits, auto.manager.resources.state.position.copy(),
                               np.array(b.free).reshape(-1, 2), where_prior)
