"""The compiled command check against the bounds written out in NumPy, on commands built to hit every bound,
alone and together (the manager's and REMOTE's own tests check the words, the fallback and the refusal)."""

import numpy as np
import pytest

# private to control/: the compiled kernel itself, whose contract these tests pin beside its NumPy statement
from humanoid_prime.control._tick import (
    ABOVE,
    BELOW,
    BEYOND,
    NEGATIVE_GAIN,
    NON_FINITE,
    OK,
    SHAPE,
    CommandCheck,
    Inbox,
    OutputCheck,
)
from humanoid_prime.control.interfaces import POSITION_MARGIN


def reference(data, lower, upper, maximum):
    """The bounds (control/bounds.py's docstring) in NumPy: (what, row, col) and the clipped data."""
    data = data.copy()
    bad = np.argwhere(~np.isfinite(data))
    if bad.size:
        return (NON_FINITE, *bad[0]), data
    for row in (3, 4):
        if data[row].min() < 0.0:
            return (NEGATIVE_GAIN, row, int(np.argmin(data[row]))), data
    for row in range(1, 5):
        beyond = np.abs(data[row]) > maximum[row - 1]
        if beyond.any():
            return (BEYOND, row, int(np.argmax(beyond))), data
    for what, outside in ((BELOW, data[0] < lower - POSITION_MARGIN), (ABOVE, data[0] > upper + POSITION_MARGIN)):
        if outside.any():
            return (what, 0, int(np.argmax(outside))), data
    np.clip(data[0], lower, upper, out=data[0])
    return (OK, -1, -1), data


def commands(n, count, seed):
    """Mostly valid commands, each with a few of the bounds' cases planted: NaN and inf, negative gains (some
    tied), values just past a maximum either way, targets within and beyond the margin on either side, with and
    without stiffness."""
    rng = np.random.default_rng(seed)
    lower, upper = -rng.uniform(0.2, 2.0, n), rng.uniform(0.2, 2.0, n)
    maximum = np.vstack([rng.uniform(1.0, 7.0, n), rng.uniform(1.0, 50.0, n), rng.uniform(10.0, 500.0, n),
                         rng.uniform(5.0, 50.0, n)])
    for _ in range(count):
        data = np.vstack([rng.uniform(lower, upper), rng.uniform(-maximum[0], maximum[0]),
                          rng.uniform(-maximum[1], maximum[1]), rng.uniform(0, maximum[2]) * (rng.random(n) < 0.7),
                          rng.uniform(0, maximum[3])])
        for _ in range(rng.integers(0, 3)):
            j, kind = rng.integers(n), rng.integers(7)
            if kind == 0:
                data[rng.integers(5), j] = rng.choice([np.nan, np.inf, -np.inf])
            elif kind == 1:
                data[rng.integers(3, 5), j] = -rng.choice([0.5, 1.0])
            elif kind == 2:
                row = rng.integers(1, 5)
                data[row, j] = maximum[row - 1, j] * rng.choice([1.0, 1.0001, -1.0001, 1e300])
            else:
                edge = lower[j] if kind in (3, 4) else upper[j]
                sign = -1.0 if kind in (3, 4) else 1.0
                data[0, j] = edge + sign * POSITION_MARGIN * rng.choice([0.5, 1.0, 1.5, 1e300])
        yield data, lower, upper, maximum


@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_check_finds_and_clips_exactly_what_the_bounds_say(seed):
    n = 14
    seen = set()
    for data, lower, upper, maximum in commands(n, 3000, seed):
        check = CommandCheck(lower, upper, maximum, POSITION_MARGIN)
        expected, clipped = reference(data, lower, upper, maximum)
        command = data.copy()
        found = check.check(command)
        assert (found, check.row, check.col) == expected, data
        np.testing.assert_array_equal(command, clipped if found == OK else data)
        seen.add(found)
    assert seen == {OK, NON_FINITE, NEGATIVE_GAIN, BEYOND, BELOW, ABOVE}


def bounds(n=14):
    return CommandCheck(-np.ones(n), np.ones(n), np.ones((4, n)), POSITION_MARGIN)


def test_propose_and_commit_copy_all_five_rows_between_command_and_proposal():
    n = 14
    proposal, command = np.zeros((5, n)), np.arange(5.0 * n).reshape(5, n)
    output = OutputCheck(proposal, command, bounds(n))
    output.propose()
    np.testing.assert_array_equal(proposal, command)
    proposal[:] = -1.0
    output.commit()
    np.testing.assert_array_equal(command, np.full((5, n), -1.0))


def test_the_output_check_checks_the_proposal_in_place():
    n = 14
    proposal = np.zeros((5, n))
    proposal[0, 3] = 1.0 + POSITION_MARGIN / 2
    check = bounds(n)
    assert OutputCheck(proposal, np.zeros((5, n)), check).check() == OK
    assert proposal[0, 3] == 1.0
    proposal[3, 7] = 2.0
    assert OutputCheck(proposal, np.zeros((5, n)), check).check() == BEYOND and (check.row, check.col) == (3, 7)


def test_the_inbox_takes_rows_that_pass_and_leaves_the_inbox_as_it_was_otherwise():
    n = 14
    inbox = np.full((5, n), 7.0)
    check = bounds(n)
    take = Inbox(inbox, check).take
    rows = [[0.5] * n, [0.0] * n, [0.0] * n, [1] * n, np.zeros(n, dtype=np.float32)]  # lists, ints, float32
    assert take(*rows) == OK
    np.testing.assert_array_equal(inbox, np.array(rows, dtype=np.float64))
    before = inbox.copy()
    rows[1] = [0.0] * (n - 1) + [2.0]
    assert take(*rows) == BEYOND and (check.row, check.col) == (1, n - 1)
    np.testing.assert_array_equal(inbox, before)


@pytest.mark.parametrize(("row", "value"), [(4, np.ones((14, 1))), (4, 1.0), (2, ["x"] * 14), (2, [[0.0, 1.0]] * 14),
                                            (1, None), (0, np.zeros(13))])
def test_the_inbox_refuses_a_row_that_is_not_one_number_per_joint(row, value):
    rows = [np.zeros(14) for _ in range(5)]
    rows[row] = value
    check = bounds()
    assert Inbox(np.zeros((5, 14)), check).take(*rows) == SHAPE and check.row == row


def test_a_strided_row_is_taken_as_its_values():
    inbox = np.zeros((5, 14))
    rows = [np.zeros(14) for _ in range(5)]
    rows[0] = np.linspace(-0.5, 0.5, 28)[::2]
    assert Inbox(inbox, bounds()).take(*rows) == OK
    np.testing.assert_array_equal(inbox[0], rows[0])


@pytest.mark.parametrize(("shape", "limits"), [((4, 14), 14), ((5, 14), 13)])
def test_it_refuses_arrays_of_another_shape(shape, limits):
    with pytest.raises(ValueError, match="5 x|joints"):
        OutputCheck(np.zeros(shape), np.zeros((5, 14)),
                    CommandCheck(np.zeros(limits), np.ones(limits), np.ones((4, limits)), 0.0))
