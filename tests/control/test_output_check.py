"""The compiled output check against the rules written out in NumPy, on proposals built to hit every rule,
alone and together (the manager's own tests check the words and the fallback)."""

import numpy as np
import pytest

from humanoid_prime.control._tick import ABOVE, BELOW, EFFORT, NEGATIVE_GAIN, NON_FINITE, OK, OutputCheck
from humanoid_prime.control.interfaces import POSITION_MARGIN


def reference(data, lower, upper, effort_limit):
    """The output check (control/manager.py's docstring) in NumPy: (what, row, col) and the clipped data."""
    data = data.copy()
    bad = np.argwhere(~np.isfinite(data))
    if bad.size:
        return (NON_FINITE, *bad[0]), data
    for row in (3, 4):
        if data[row].min() < 0.0:
            return (NEGATIVE_GAIN, row, int(np.argmin(data[row]))), data
    beyond = np.abs(data[2]) > effort_limit
    if beyond.any():
        return (EFFORT, 2, int(np.argmax(beyond))), data
    stiff = data[3] > 0.0
    for what, outside in ((BELOW, data[0] < lower - POSITION_MARGIN), (ABOVE, data[0] > upper + POSITION_MARGIN)):
        outside &= stiff
        if outside.any():
            return (what, 0, int(np.argmax(outside))), data
    np.clip(data[0], lower, upper, out=data[0], where=stiff)
    return (OK, -1, -1), data


def proposals(n, count, seed):
    """Mostly valid commands, each with a few of the rules' cases planted: NaN and inf, negative gains (some
    tied), efforts just past the limit, targets within and beyond the margin on either side, with and without
    stiffness."""
    rng = np.random.default_rng(seed)
    lower, upper = -rng.uniform(0.2, 2.0, n), rng.uniform(0.2, 2.0, n)
    effort_limit = rng.uniform(1.0, 50.0, n)
    for _ in range(count):
        data = np.vstack([rng.uniform(lower, upper), rng.normal(0, 1, n), rng.uniform(-effort_limit, effort_limit),
                          rng.uniform(0, 20, n) * (rng.random(n) < 0.7), rng.uniform(0, 3, n)])
        for _ in range(rng.integers(0, 3)):
            j, kind = rng.integers(n), rng.integers(7)
            if kind == 0:
                data[rng.integers(5), j] = rng.choice([np.nan, np.inf, -np.inf])
            elif kind == 1:
                data[rng.integers(3, 5), j] = -rng.choice([0.5, 1.0])
            elif kind == 2:
                data[2, j] = effort_limit[j] * rng.choice([1.0, 1.0001, -1.0001])
            else:
                edge = lower[j] if kind in (3, 4) else upper[j]
                sign = -1.0 if kind in (3, 4) else 1.0
                data[0, j] = edge + sign * POSITION_MARGIN * rng.choice([0.5, 1.0, 1.5])
        yield data, lower, upper, effort_limit


@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_check_finds_and_clips_exactly_what_the_rules_say(seed):
    n = 14
    seen = set()
    for data, lower, upper, effort_limit in proposals(n, 3000, seed):
        proposal, command = data.copy(), np.zeros((5, n))
        check = OutputCheck(proposal, command, lower, upper, effort_limit, POSITION_MARGIN)
        expected, clipped = reference(data, lower, upper, effort_limit)
        found = check.check()
        assert (found, check.row, check.col) == expected, data
        if found == OK:
            np.testing.assert_array_equal(proposal, clipped)
        seen.add(found)
    assert seen == {OK, NON_FINITE, NEGATIVE_GAIN, EFFORT, BELOW, ABOVE}


def test_propose_and_commit_copy_all_five_rows_between_command_and_proposal():
    n = 14
    proposal, command = np.zeros((5, n)), np.arange(5.0 * n).reshape(5, n)
    check = OutputCheck(proposal, command, -np.ones(n), np.ones(n), np.ones(n), POSITION_MARGIN)
    check.propose()
    np.testing.assert_array_equal(proposal, command)
    proposal[:] = -1.0
    check.commit()
    np.testing.assert_array_equal(command, np.full((5, n), -1.0))


@pytest.mark.parametrize(("shape", "limits"), [((4, 14), 14), ((5, 14), 13)])
def test_it_refuses_arrays_of_another_shape(shape, limits):
    with pytest.raises(ValueError, match="5 x 14|14 joints"):
        OutputCheck(np.zeros(shape), np.zeros((5, 14)), np.zeros(limits), np.ones(limits), np.ones(limits), 0.0)
