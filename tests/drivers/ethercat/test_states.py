"""AL state changes waited for as long as ETG.2000's timeouts let them take, and the end of a wait said truly: refused
(with the AL status code), still changing, or not answering."""

from __future__ import annotations

from doubles.link import EmulatedClock
from humanoid_prime.drivers.ethercat.states import ASK_AGAIN_S, PREOP_TIMEOUT_S, SAFEOP_OP_TIMEOUT_S, await_state
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, AlState


class Slaves:
    """Slaves whose AL states change when the test says, on an emulated clock."""

    def __init__(self, clock: EmulatedClock, states: list[tuple[int, int] | None]) -> None:
        self.clock = clock
        self.states = states
        self.changes: dict[int, tuple[float, tuple[int, int]]] = {}  # position -> (when, state)
        self.asked: list[tuple[float, int, int]] = []

    def read(self) -> list[tuple[int, int] | None]:
        for k, (when, state) in list(self.changes.items()):
            if self.clock() >= when:
                self.states[k] = state
                del self.changes[k]
        return list(self.states)

    def ask(self, k: int, state: int) -> None:
        self.asked.append((self.clock(), k, state))


def wait(slaves: Slaves, want: int):
    return await_state(slaves.read, slaves.ask, len(slaves.states), want, clock=slaves.clock, sleep=slaves.clock.sleep)


def test_a_slave_that_takes_two_and_a_half_seconds_to_pre_op_is_waited_for():
    clock = EmulatedClock()
    slaves = Slaves(clock, [(AlState.PRE_OP, 0), (AlState.INIT, 0)])
    slaves.changes[1] = (clock() + 2.5, (AlState.PRE_OP, 0x0050))  # a code left set after success: ignored
    result = wait(slaves, AlState.PRE_OP)
    assert result.reached and 2.5 <= result.seconds < 2.6


def test_a_slow_slave_is_asked_again_every_half_second_while_it_has_not_changed():
    clock = EmulatedClock()
    began = clock()
    slaves = Slaves(clock, [(AlState.PRE_OP, 0)])
    slaves.changes[0] = (began + 1.2, (AlState.SAFE_OP, 0))
    assert wait(slaves, AlState.SAFE_OP).reached
    assert [round(when - began, 2) for when, _k, _s in slaves.asked] == [ASK_AGAIN_S, 2 * ASK_AGAIN_S]


def test_a_slave_still_changing_after_the_standard_s_time_is_said_to_be_slow_not_refused():
    clock = EmulatedClock()
    slaves = Slaves(clock, [(AlState.PRE_OP, 0), (AlState.INIT, 0x0016)])  # an old code, no error indicated
    result = wait(slaves, AlState.PRE_OP)
    assert not result.reached and PREOP_TIMEOUT_S < result.seconds < PREOP_TIMEOUT_S + 0.01
    assert result.describe() == ("ring 1 still in INIT after 3.0 s, no error indicated (slow, not refused; "
                                 "ETG.2000's PreopTimeout is 3 s)")


def test_a_refusal_ends_the_wait_at_once_and_names_its_al_status_code():
    clock = EmulatedClock()
    began = clock()
    slaves = Slaves(clock, [(AlState.PRE_OP, 0), (AlState.SAFE_OP, 0)])
    slaves.changes[0] = (began + 0.2, (AlState.PRE_OP | AL_ERROR, 0x001D))
    result = wait(slaves, AlState.SAFE_OP)
    assert result.refused == [0] and result.seconds < 0.21
    assert result.describe() == "ring 0 refused SAFE-OP: PRE-OP + ERROR, AL status 0x001D invalid output configuration"


def test_safe_op_is_given_ten_seconds_and_a_slave_that_does_not_answer_is_named():
    clock = EmulatedClock()
    slaves = Slaves(clock, [(AlState.PRE_OP, 0), None])
    result = wait(slaves, AlState.SAFE_OP)
    assert SAFEOP_OP_TIMEOUT_S < result.seconds < SAFEOP_OP_TIMEOUT_S + 0.01
    assert "ring 1 does not answer" in result.describe()
