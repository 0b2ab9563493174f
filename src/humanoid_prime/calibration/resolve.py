"""The directions of a hands-free calibration, settled at its end (``calibration.auto``; DESIGN §5), once every
joint's offset is known, proximal first: from the limits (an asymmetric range) and the gravity measured along
each sweep (``calibration.direction``, ``settle``); where neither tells, a robot's prior calibration whose windows
held both stops (the same joint as calibrated before: a recalibration asks only where the stops moved), else one
small motion and a plain question for each joint whose proximal joints are known (``ask``), or the prior's with
``assume_direction``. A flip is
written only on such evidence, and reported.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from humanoid_prime.calibration.approach import JointRun, Move
from humanoid_prime.calibration.direction import direction_from_gravity, view_of
from humanoid_prime.calibration.joint import Sweep, moving
from humanoid_prime.calibration.math import flip_direction
from humanoid_prime.calibration.operator import Unattended
from humanoid_prime.calibration.sequence import Aborted, JointFailed, Steps
from humanoid_prime.errors import PrimeError

if TYPE_CHECKING:
    from humanoid_prime.calibration.auto import AutoCalibration

PROMPT_RAD = 0.15  # the prompted motion that asks the operator for a direction
GRAVITY_SAMPLES = 60

Floats = npt.NDArray[np.float64]


def proximal_first(auto: AutoCalibration, joint: str) -> tuple[int, int]:
    return (0 if joint.startswith("left_") else 1, auto.robot.index(joint))


def settle(auto: AutoCalibration) -> None:
    """Proximal first: each measured joint's direction from its limits and from the gravity measured along its
    sweep, fitted with the model in the configuration the other joints had then (their calibration known by now,
    the proximal ones' directions settled just before)."""
    for joint in sorted(auto.sweeps, key=lambda j: proximal_first(auto, j)):
        outcome, sweep = auto.outcomes[joint], auto.sweeps[joint]
        if outcome.status != "direction_unknown":
            continue
        by_gravity, gravity_text = gravity_verdict(auto, joint, sweep)
        verdicts = {v for v in (sweep.by_limits, by_gravity) if v is not None}
        if len(verdicts) > 1:
            outcome.message = f"the limits and gravity disagree about the direction ({gravity_text})"
            outcome.calibration = sweep.same
            continue
        if not verdicts and sweep.where_prior:  # the same joint as calibrated before: its wiring is as it was
            outcome.calibration = sweep.same
            outcome.direction_source = "prior calibration"
            outcome.status = "done"
            outcome.message = (f"direction from the prior calibration: both stops are where it put them, and "
                               f"the physics cannot tell ({gravity_text})")
            auto.know(auto.robot.index(joint), outcome.calibration, settled=True)
            continue
        if not verdicts:
            outcome.message = f"the physics cannot tell the direction ({gravity_text})"
            continue
        verdict = verdicts.pop()
        outcome.calibration = sweep.same if verdict == 1 else sweep.flipped
        outcome.direction_source = " and ".join(name for name, v in (("limits", sweep.by_limits),
                                                                      ("gravity", by_gravity)) if v is not None)
        outcome.status = "done"
        outcome.message = f"direction from the {outcome.direction_source}; {gravity_text}"
        auto.know(auto.robot.index(joint), outcome.calibration, settled=True)


def gravity_verdict(auto: AutoCalibration, joint: str, sweep: Sweep) -> tuple[int | None, str]:
    """Fit the effort measured along the sweep between the stops with the model's gravity under either
    direction."""
    if len(sweep.samples) < 10:
        return None, "too few free-motion samples"
    i = auto.robot.index(joint)
    samples = sweep.samples
    take = np.linspace(0, len(samples) - 1, min(GRAVITY_SAMPLES, len(samples))).astype(int)
    samples = samples[take]
    q = sweep.config.copy()
    predicted: dict[int, Floats] = {}
    for hypothesis, cal in ((1, sweep.same), (-1, sweep.flipped)):
        direction, offset = auto.direction.copy(), auto.offset.copy()
        direction[i], offset[i] = cal.direction, cal.homing_offset
        values = []
        for position in samples[:, 0]:
            q[i] = position
            values.append(float(auto.host_gravity(q, auto.model, direction, offset)[i]))
        predicted[hypothesis] = np.array(values)
    return direction_from_gravity(samples[:, 0], samples[:, 1], predicted)


def unknown(auto: AutoCalibration) -> list[str]:
    """The joints measured whose direction is still to be asked, proximal first."""
    joints = [j for j in auto.joints if auto.outcomes[j].status == "direction_unknown"
              and auto.outcomes[j].calibration is not None]
    return sorted(joints, key=lambda j: proximal_first(auto, j))


def may_ask(auto: AutoCalibration, joint: str) -> bool:
    """Whether ``joint``'s question can be asked now: its axis in the world depends on its proximal joints'
    calibration, the operator is there, the direction is not assumed; says in its outcome why not."""
    outcome = auto.outcomes[joint]
    waiting = [j for j in auto.joints if proximal_first(auto, j)[0] == proximal_first(auto, joint)[0]
               and auto.robot.index(j) < auto.robot.index(joint) and not auto.outcomes[j].done]
    if auto.assume_direction:
        outcome.status = "done"
        outcome.direction_source = "assumed (--assume-direction)"
        outcome.message = "direction as in the prior file (assumed); " + outcome.message
        return False
    if waiting:
        outcome.message += f"; not asked: {', '.join(waiting)} must be calibrated first"
        return False
    if isinstance(auto.operator, Unattended):
        outcome.message += "; nobody to ask: give --assume-direction or run at the robot"
        return False
    return True


def ask(auto: AutoCalibration, joint: str) -> Steps:
    """One small motion toward the middle of the range (at the travel speed: both stops are known), the
    question, and back."""
    outcome = auto.outcomes[joint]
    i = auto.robot.index(joint)
    state = auto.manager.resources.state
    assert outcome.calibration is not None and outcome.stops is not None
    middle = 0.5 * (outcome.stops[0] + outcome.stops[1])
    answers: list[bool | None] = []
    runs: list[JointRun] = []
    side = 1

    def work(run: JointRun) -> Steps:
        nonlocal side
        runs.append(run)
        start = float(state.position[i])
        side = 1 if middle >= start else -1
        view, where = view_of(auto.model.axis(joint, auto.description_angles(state.position).copy()))
        auto.operator.watch(joint)
        moved = Move(run, start + side * PROMPT_RAD, start, leaving=True, kind="question")  # it may rest
        yield moved
        answers.append(auto.operator.turned_counter_clockwise(joint, view, where))
        yield Move(run, start, moved.target, kind="question")

    began = state.stamp
    try:
        yield from moving(auto, joint, work)
    except JointFailed as exc:
        outcome.status, outcome.message = "failed", f"while asking for its direction: {exc}"
        return
    except Aborted as exc:
        outcome.status, outcome.message = "aborted", f"while asking for its direction: {exc}"
        return
    except PrimeError as exc:
        outcome.status, outcome.message = "aborted", f"while asking for its direction: {exc}"
        auto.abort(str(exc))
        return
    finally:
        outcome.seconds += state.stamp - began
        for run in runs:
            for kind, seconds in run.seconds.items():
                outcome.times[kind] = outcome.times.get(kind, 0.0) + seconds
    answer = answers[0] if answers else None
    if answer is None:
        outcome.message += "; the direction question was not answered"
        return
    # With the prior's direction, a positive host motion turns the joint positive: counter-clockwise here.
    same = answer == (side > 0)
    if not same:
        spec = auto.robot.joints[i]
        outcome.calibration = flip_direction(outcome.calibration, spec.lower, spec.upper)
    outcome.status = "done"
    outcome.direction_source = auto.operator.answered_by
    outcome.message = (f"direction from {auto.operator.answered_by}"
                       + ("" if same else ": it is wired the other way round, the flip is written"))
    auto.know(i, outcome.calibration, settled=True)
