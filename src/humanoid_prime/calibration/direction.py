"""A joint's direction from physics where it can tell (DESIGN §5), and the plain question where it cannot.

``direction_from_limits``: two stops measured in the host frame (the prior's direction, offset 0) give one
calibration with the prior's direction and its flip; an asymmetric range leaves one of the two offsets plausible.
``direction_from_gravity``: the effort measured along a sweep between the stops against the model's gravity
under either direction. ``view_of``: where a person stands to see a rotation about an axis, for the question.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from humanoid_prime.calibration.math import flip_direction, offset_from_sweep
from humanoid_prime.config.calibration import JointCalibration
from humanoid_prime.config.robot import JointSpec

MIN_ASYMMETRY_RAD = 0.5  # limits whose sum is at least this tell the direction by themselves
PLAUSIBILITY_MARGIN_RAD = 0.1  # the plausible offset must be this far under half the asymmetry
GRAVITY_MIN_SEPARATION_NM = 0.15  # the two directions' gravity curves must differ this much (RMS) to tell
GRAVITY_RESIDUAL_RATIO = 2.0  # and the wrong one must fit this much worse,
GRAVITY_SCALE = (0.6, 1.6)  # the right one's amplitude near the model's,
GRAVITY_UNEXPLAINED = 0.3  # leaving at most this share of the measured spread unexplained


def direction_from_limits(prior_direction: int, stops: tuple[float, float], spec: JointSpec
                          ) -> tuple[JointCalibration, JointCalibration, int | None]:
    """The calibration the stops give with the prior direction and flipped, and which one an asymmetric range
    picks: +1 the prior's, -1 the flipped one, None when the range cannot tell (its limits are too symmetric,
    or neither offset is plausible)."""
    same = JointCalibration(prior_direction, offset_from_sweep(stops[0], stops[1], spec.lower, spec.upper,
                                                               prior_direction))
    flipped = flip_direction(same, spec.lower, spec.upper)
    asymmetry = abs(spec.lower + spec.upper)
    if asymmetry < MIN_ASYMMETRY_RAD:
        return same, flipped, None
    # The two offsets differ by the asymmetry: an offset under half of it leaves the other beyond half of it.
    for verdict, cal in ((1, same), (-1, flipped)):
        if abs(cal.homing_offset) < 0.5 * asymmetry - PLAUSIBILITY_MARGIN_RAD:
            return same, flipped, verdict
    return same, flipped, None


def direction_from_gravity(samples: npt.NDArray[np.float64], measured: npt.NDArray[np.float64],
                           predicted: Mapping[int, npt.NDArray[np.float64]]
                           ) -> tuple[int | None, str]:
    """Which hypothesis (+1 the prior's direction, -1 flipped) the effort measured along a sweep fits: each
    prediction is fitted with a scale and an offset (friction). A verdict needs the two predictions to differ,
    the better one to fit well (its scale near 1, most of the measured variation explained: the model's
    configuration of the other joints is right) and the other to fit clearly worse; otherwise None.
    ``samples`` only sizes the fit."""
    if samples.size < 10:
        return None, "too few free-motion samples"
    plus, minus = predicted[1], predicted[-1]
    separation = float(np.std((plus - plus.mean()) - (minus - minus.mean())))
    if separation < GRAVITY_MIN_SEPARATION_NM:
        return None, f"gravity cannot tell (the two directions differ by {separation:.3f} Nm RMS along the sweep)"
    residuals, good = {}, {}
    spread = float(np.std(measured))
    for hypothesis, prediction in predicted.items():
        design = np.stack([prediction, np.ones_like(prediction)], axis=1)
        solution, *_ = np.linalg.lstsq(design, measured, rcond=None)
        residual = float(np.sqrt(np.mean((measured - design @ solution) ** 2)))
        residuals[hypothesis] = residual
        good[hypothesis] = (GRAVITY_SCALE[0] <= solution[0] <= GRAVITY_SCALE[1]
                            and residual <= GRAVITY_UNEXPLAINED * spread)
    best = min(residuals, key=residuals.__getitem__)
    text = f"{residuals[1]:.3f} and {residuals[-1]:.3f} Nm RMS for the prior and the flipped direction"
    if not good[best] or residuals[-best] < GRAVITY_RESIDUAL_RATIO * max(residuals[best], 1e-3):
        return None, f"gravity unclear ({text})"
    return best, f"gravity fits {'the prior' if best == 1 else 'the flipped'} direction ({text})"


VIEWS = {(0, 1): "in front of the robot", (0, -1): "behind the robot", (1, 1): "at the robot's left side",
         (1, -1): "at the robot's right side", (2, 1): "above the robot", (2, -1): "below the robot"}


def view_of(axis: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], str]:
    """The world axis a person looks along to see a rotation about ``axis`` best, pointing at them (a positive
    rotation turns counter-clockwise for them), and where they stand, in words."""
    k = int(np.argmax(np.abs(axis)))
    sign = 1 if axis[k] >= 0 else -1
    view = np.zeros(3)
    view[k] = sign
    return view, VIEWS[(k, sign)]
