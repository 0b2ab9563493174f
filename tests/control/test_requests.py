"""The hand-over of requests from other threads to the control loop (``LoopRequests``), the fallback chain
(``FallbackChain``) and the merged flags of /safety_status (``FlagSources``), each through its own interface."""

import threading

import pytest

from humanoid_prime.control.controller import Controller
from humanoid_prime.control.fallback import FallbackChain
from humanoid_prime.control.flags import FlagSources, Level, SafetyFlags
from humanoid_prime.control.requests import LoopRequests
from humanoid_prime.errors import PrimeError
from humanoid_prime.modes import Mode


class Still(Controller):
    def update(self, now, dt, state, command) -> None:
        command.data[:] = 0.0


STANDBY, DAMPING, ZERO = Still("standby", Mode.STANDBY), Still("damping", Mode.DAMPING), Still("zero", Mode.ZERO_TORQUE)
PASSIVE, TASK = Still("passive", None), Still("calibration", None)


def test_the_latest_request_wins_and_the_loop_takes_it_once():
    requests = LoopRequests()
    assert not requests.waiting
    first, second = requests.ask(STANDBY), requests.ask(DAMPING)
    assert second == first + 1 and requests.waiting
    assert requests.take() == (DAMPING, False)
    assert requests.take() == (None, False) and not requests.waiting


def test_a_refused_mode_raises_its_reason_and_leaves_the_waiting_request():
    requests = LoopRequests()
    requests.ask(DAMPING)
    requests.refuse([Mode.STANDBY], "the calibration is the identity template")
    with pytest.raises(PrimeError, match="^STANDBY refused: the calibration is the identity template$"):
        requests.ask(STANDBY)
    assert requests.take() == (DAMPING, False)


def test_a_reset_is_taken_with_the_next_tick():
    requests = LoopRequests()
    requests.ask_reset()
    assert requests.waiting and requests.take() == (None, True) and not requests.waiting


def test_what_came_of_a_request_is_told_to_its_waiter_and_an_older_one_learns_it_was_superseded():
    requests = LoopRequests()
    older, ticket = requests.ask(STANDBY), requests.ask(DAMPING)
    assert requests.wait(ticket, 0.0) is None  # no tick has applied it
    requests.take()
    assert requests.taken
    requests.tell(Mode.ZERO_TORQUE, "damping: ValueError: boom")
    outcome = requests.wait(ticket, 0.0)
    assert (outcome.requested, outcome.active) == (Mode.DAMPING, Mode.ZERO_TORQUE)
    assert outcome.reason == "fell back to ZERO_TORQUE: damping: ValueError: boom"
    assert requests.wait(older, 0.0).reason == "superseded by a later request for DAMPING"


def test_a_waiter_on_another_thread_is_woken_by_the_tick_that_applied_its_request():
    requests = LoopRequests()
    ticket = requests.ask(STANDBY)
    outcomes = []
    waiter = threading.Thread(target=lambda: outcomes.append(requests.wait(ticket, 60.0)))
    waiter.start()
    requests.take()
    requests.tell(Mode.STANDBY, "")
    waiter.join(60.0)
    assert [(o.requested, o.active, o.reason) for o in outcomes] == [(Mode.STANDBY, Mode.STANDBY, "")]


def test_a_task_is_handed_back_only_while_it_is_active_or_asked_for():
    requests = LoopRequests()
    requests.hand_back(TASK, PASSIVE, active=PASSIVE)  # neither active nor waiting: nothing to hand back
    assert not requests.waiting
    requests.ask(TASK)
    requests.hand_back(TASK, PASSIVE, active=PASSIVE)
    assert requests.take() == (PASSIVE, False)
    requests.hand_back(TASK, PASSIVE, active=TASK)
    assert requests.take() == (PASSIVE, False)


def test_modes_fall_back_by_the_table_and_tasks_to_the_passive_command():
    chain = FallbackChain({Mode.DAMPING: DAMPING, Mode.ZERO_TORQUE: ZERO}, PASSIVE, SafetyFlags("manager"))
    assert [chain.after(c) for c in (STANDBY, DAMPING, ZERO, TASK, PASSIVE)] == [DAMPING, ZERO, None, PASSIVE, None]


def test_each_fallback_is_recorded_and_the_latest_flagged():
    flags = SafetyFlags("manager")
    chain = FallbackChain({}, PASSIVE, flags)
    assert chain.last_reason == "no mode controller is active"
    chain.record(7, STANDBY, DAMPING, "standby: ValueError: boom")
    chain.record(9, TASK, PASSIVE, "calibration: it gave up")
    assert chain.records == [{"tick": 7, "from": "STANDBY", "to": "DAMPING", "reason": "standby: ValueError: boom"},
                             {"tick": 9, "from": "calibration", "to": "passive", "reason": "calibration: it gave up"}]
    assert flags.flags == {"fallback": "calibration: it gave up; fell back from calibration to passive"}
    assert chain.last_reason == "calibration: it gave up"


def test_flags_are_merged_under_their_sources_names_only_when_one_changed():
    drives, manager = SafetyFlags("drives"), SafetyFlags("manager")
    sources = FlagSources([drives, manager])
    assert sources.changed() == ({}, {})
    assert sources.changed() is None
    drives.set_flag("ring3/fault", "drive fault 0x7500")
    manager.set_flag("fallback", "fell back", Level.WARN)
    assert sources.changed() == ({"drives/ring3/fault": "drive fault 0x7500", "manager/fallback": "fell back"},
                                 {"drives/ring3/fault": Level.ERROR, "manager/fallback": Level.WARN})
    assert sources.changed() is None
    late = SafetyFlags("impedance")
    sources.add(late)
    assert sources.names == ["drives", "manager", "impedance"] and sources.changed() is not None
