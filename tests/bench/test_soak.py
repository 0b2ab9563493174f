"""The soak's verdicts: each injected fault judged from the run's own fault history, and every flag no injection
explains reported."""

import threading
import time

from humanoid_prime.bench.soak_faults import FAULTS, LOST_RING, SETTLE_S
from humanoid_prime.bench.soak_judge import Injection, explained, judge
from humanoid_prime.control.flags import Level
from humanoid_prime.runtime.report import FaultRecord

BY_NAME = {fault.name: fault for fault in FAULTS}
LOST = BY_NAME["slave lost and returned"]
REFERENCE_LOST = BY_NAME["reference clock slave lost and returned"]
SILENT = BY_NAME["silent Sito"]
DRIVE_FAULT = BY_NAME["drive fault 0x7500"]
ONE_FRAME = BY_NAME["one EtherCAT frame lost"]
SDO_ABORT = BY_NAME["SDO abort"]


class LoopManager:
    """The controller manager's part in a reset: asked from the injector's thread, applied a tick later."""

    def __init__(self, asked=lambda: None) -> None:
        self.resets = 0
        self.update_rate = 50.0
        self._asked = asked

    def request_reset(self) -> None:
        self._asked()
        threading.Timer(0.05, self._apply).start()

    def _apply(self) -> None:
        self.resets += 1


def record(key, since, until=None, level=Level.ERROR):
    return FaultRecord(key, "text", level, since, until)


def test_a_flag_raised_and_cleared_after_the_injection_is_recovered():
    injection = Injection(SILENT, at_s=10.0, done_s=11.0)
    judge(injection, [record("PrimeSitoCAN/x/rx_timeout/22", 10.3, 11.1)], ended_s=60.0)
    assert injection.outcome == "recovered" == SILENT.expect


def test_a_flag_still_up_long_after_the_fault_ended_is_held():
    injection = Injection(SILENT, at_s=10.0, done_s=11.0)
    judge(injection, [record("PrimeSitoCAN/x/rx_timeout/22", 10.3)], ended_s=60.0)
    assert injection.outcome == "held"


def test_a_fault_nobody_flagged_is_not_flagged():
    injection = Injection(SILENT, at_s=10.0, done_s=11.0)
    judge(injection, [record("PrimeSitoCAN/x/rx_timeout/22", 11.0 + SETTLE_S + 1, 20.0)], ended_s=60.0)
    assert injection.outcome == "not flagged"


def test_a_returned_slave_is_latched_when_its_drive_waited_disabled_for_the_operators_reset():
    injection = Injection(LOST, at_s=10.0, done_s=11.0)
    judge(injection, [record("PrimeEtherCATSide/ethercat/ring9/lost", 10.1, 18.0),
                      record("PrimeEtherCATSide/ethercat/ring9/disabled", 18.0, 18.1)], ended_s=60.0, resets=[18.05])
    assert injection.outcome == "latched" == LOST.expect


def test_the_other_drives_watchdog_faults_are_consequences_of_losing_the_reference_clock_slave_not_surprises():
    injection = Injection(REFERENCE_LOST, at_s=10.0, done_s=11.0)
    flags = [record("PrimeEtherCATSide/ethercat/wkc", 10.1, 12.0),
             *(record(f"PrimeEtherCATSide/ethercat/ring{k}/fault", 10.2, 24.0) for k in range(1, 10)),
             record("PrimeEtherCATSide/ethercat/ring0/disabled", 20.0, 24.0)]
    judge(injection, flags, ended_s=60.0, resets=[23.9])
    assert injection.outcome == "latched" == REFERENCE_LOST.expect
    assert all(explained(r, [injection], flags) for r in flags)
    assert not explained(record("PrimeEtherCATSide/ethercat/ring4/fault", 40.0), [injection], flags)
    assert not explained(record("PrimeEtherCATSide/ethercat/ring4/fault", 10.2), [Injection(LOST, 10.0, 11.0)], [])


def test_a_returned_drive_released_on_gains_nobody_chose_is_not_as_designed():
    injection = Injection(LOST, at_s=10.0, done_s=11.0, released_wrong="ring 9 was released with gate 0")
    judge(injection, [record("PrimeEtherCATSide/ethercat/ring9/disabled", 18.0, 18.1)], ended_s=60.0, resets=[18.05])
    assert injection.outcome == "released on settings nobody chose" != LOST.expect


class _Impedance:
    """What the soak's check reads of the impedance manager: the mode applied last and its registers."""

    def __init__(self, targets):
        from humanoid_prime.modes import Mode

        self.mode, self.reports, self.targets = Mode.STANDBY, [], {Mode.STANDBY: targets}

    def wait_idle(self, timeout):
        return True


class _Control:
    def __init__(self, drive):
        self.drive = drive

    def slave(self, position):
        return {"drive": self.drive}


def test_the_soak_checks_the_returned_drive_holds_the_gate_and_the_applied_modes_registers():
    from types import SimpleNamespace

    from humanoid_prime.bench.soak_faults import LOST_RING
    from humanoid_prime.drivers.erob.gains import ErobRegisters

    session = SimpleNamespace(impedance=_Impedance({LOST_RING: ErobRegisters(pos_reg=515, vel_reg=19, integral=5)}))
    restored = {"gate": 1, "pos_reg": 515, "vel_reg": 19, "integral": 5}
    assert LOST.verify(_Control(restored), session) is None
    problem = LOST.verify(_Control({**restored, "gate": 0, "pos_reg": 300, "vel_reg": 94}), session)
    assert problem == ("ring 9 was released with gate 0 and registers (300, 94, 5), not the gate 1 and STANDBY's "
                       "(515, 19, 5)")


def test_a_drive_fault_is_latched_only_when_the_operators_reset_cleared_it():
    flag = [record("PrimeEtherCATSide/ethercat/ring6/fault", 10.05, 10.5)]
    reset = Injection(DRIVE_FAULT, at_s=10.0, done_s=10.0)
    judge(reset, flag, ended_s=60.0, resets=[10.45])
    assert reset.outcome == "latched" == DRIVE_FAULT.expect
    for resets in ([], [9.0], [10.6]):  # none, one from before the fault, one after the flag had cleared
        unreset = Injection(DRIVE_FAULT, at_s=10.0, done_s=10.0)
        judge(unreset, flag, ended_s=60.0, resets=resets)
        assert unreset.outcome == "recovered without a reset"


def test_a_slave_slower_to_return_than_the_settle_time_waits_disabled_for_the_next_reset():
    """Under load the lost slave was not back in OP within its settle time, so the soak sent no reset for it;
    its drive stayed disabled until the reset sent for the next latched fault. That is latched, as designed."""
    injection = Injection(LOST, at_s=253.5, done_s=254.5)
    judge(injection, [record("PrimeEtherCATSide/ethercat/ring9/disabled", 262.0, 276.1)], ended_s=600.0,
          resets=[276.0])
    assert injection.outcome == "latched"


def test_a_latched_fault_whose_ring_was_whole_only_after_its_settle_time_is_reset_once_it_is():
    """The soak used to send a latched fault's reset only within its settle time. A returning slave whose clock
    took longer to relock left its drive held, and every later reset waited on it: the rest of the run went
    unreset (seen twice). The reset it is owed now goes out before a later injection, once the ring is whole."""
    import threading
    from types import SimpleNamespace

    import numpy as np

    from humanoid_prime.bench.soak import Operator

    requested = []
    ethercat = SimpleNamespace(master=SimpleNamespace(slave_ok=np.ones(10, dtype=bool)), restore_pending=lambda: [9])
    session = SimpleNamespace(plan=SimpleNamespace(began=0.0), ethercat=ethercat, impedance=None,
                              faults=[record("PrimeEtherCATSide/ethercat/ring9/disabled", 12.0)],
                              manager=LoopManager(lambda: requested.append(True)))
    operator = Operator(None, session, threading.Event())
    owed = Injection(LOST, at_s=10.0, done_s=11.0)
    operator.owed.append(owed)
    assert operator.owes("ethercat") and not operator.owes("can")
    operator.pay_owed()
    assert not requested and operator.owed == [owed]  # its settings are not back yet: no reset
    ethercat.restore_pending = lambda: []
    operator.pay_owed()
    assert requested == [True] and operator.owed == [] and len(operator.resets) == 1
    cleared = Injection(LOST, at_s=10.0, done_s=11.0)  # another fault's reset cleared its flag: nothing owed
    session.faults = [record("PrimeEtherCATSide/ethercat/ring9/disabled", 12.0, 30.0)]
    operator.owed.append(cleared)
    operator.pay_owed()
    assert requested == [True] and operator.owed == []


def test_no_fault_goes_onto_a_bus_that_still_waits_for_a_latched_fault_s_reset():
    """Injected onto a drive still held from the last slave loss, a fault finds its flag already up and is judged
    not flagged (seen in a soak of slave losses alone). The injector waits for the owed reset instead."""
    import threading
    from dataclasses import replace
    from types import SimpleNamespace

    import numpy as np

    from humanoid_prime.bench.soak import Injector, Operator

    injected, looked = threading.Event(), threading.Semaphore(0)
    applied_before_injection = []

    def inject(control, session) -> None:
        applied_before_injection.append(session.manager.resets)
        injected.set()

    class Watched(Operator):
        """The operator, telling each time the injector has it pay what it owes (once per turn)."""

        def pay_owed(self) -> None:
            super().pay_owed()
            looked.release()

    fault = replace(LOST, inject=inject, hold_s=0.0, end=None, verify=None)
    slave_ok = np.zeros(10, dtype=bool)
    session = SimpleNamespace(plan=SimpleNamespace(began=time.monotonic()), impedance=None,
                              ethercat=SimpleNamespace(master=SimpleNamespace(slave_ok=slave_ok),
                                                       restore_pending=lambda: []),
                              faults=[record("PrimeEtherCATSide/ethercat/ring9/disabled", 0.0)],
                              manager=LoopManager())
    stop = threading.Event()
    operator = Watched(None, session, stop)
    operator.owed.append(Injection(fault, at_s=0.0, done_s=0.0))
    injector = Injector(operator, 0.001, 600.0, faults=(fault,))
    injector.start()
    try:
        for _ in range(3):  # three turns of the injector with ring 9 still away
            assert looked.acquire(timeout=60.0)
        assert not injected.is_set() and len(operator.owed) == 1
        slave_ok[:] = True  # whole again: the owed reset goes out, then the next fault
        assert injected.wait(timeout=60.0)
        assert all(owed.at_s > 0.0 for owed in operator.owed)  # the one it was owed went out
        assert len(operator.resets) >= 1
        assert applied_before_injection[0] >= 1  # the loop applied it before the next fault went in
    finally:
        stop.set()
        injector.join(timeout=60.0)


def test_a_lost_frame_that_raised_an_error_was_not_merely_counted():
    quiet = Injection(ONE_FRAME, at_s=10.0)
    judge(quiet, [record("PrimeSitoCAN/x/invalid_frame", 10.5, 11.0, Level.WARN)], ended_s=60.0)
    assert quiet.outcome == "counted"
    loud = Injection(ONE_FRAME, at_s=10.0)
    judge(loud, [record("PrimeEtherCATSide/ethercat/wkc", 10.5, 11.0)], ended_s=60.0)
    assert loud.outcome == "flagged"


def test_an_sdo_abort_is_refused_only_with_the_read_only_abort_code():
    refused = Injection(SDO_ABORT, at_s=10.0, detail="SDO 0x6076:00 on ring 0: abort 0x06010002 (read only)")
    judge(refused, [], ended_s=60.0)
    assert refused.outcome == "refused"
    recovering = Injection(SDO_ABORT, at_s=10.0, detail="SDO 0x6076:00 on ring 0: refused: ring 0 is not in OP")
    judge(recovering, [], ended_s=60.0)
    assert recovering.outcome == "refused"  # the master's refusal: nothing reached the drive either
    lost = Injection(SDO_ABORT, at_s=10.0, detail="SDO 0x6076:00 on ring 0: no reply")
    judge(lost, [], ended_s=60.0)
    assert lost.outcome == "not refused"


def test_a_flag_is_explained_by_its_injection_or_a_consequence_in_its_window_only():
    lost = Injection(LOST, at_s=10.0, done_s=11.0)
    faults = [record("PrimeEtherCATSide/ethercat/ring9/lost", 10.2, 11.5)]
    assert explained(faults[0], [lost], faults)  # a consequence it lists
    assert explained(record("PrimeEtherCATSide/ethercat/wkc", 10.2), [lost], faults)  # a consequence it lists
    assert not explained(record("PrimeEtherCATSide/ethercat/ring3/fault", 10.2), [lost], faults)  # nobody's
    assert not explained(record("PrimeEtherCATSide/ethercat/ring9/lost", 40.0), [lost], faults)  # long after


def test_a_mode_switch_refused_while_the_returned_slave_still_recovers_is_explained_by_its_loss():
    lost = Injection(LOST, at_s=10.0, done_s=11.0)
    faults = [record("PrimeEtherCATSide/ethercat/ring9/lost", 10.2, 18.0),  # back in OP 7 s after its return
              record("PrimeEtherCATSide/ethercat/ring9/disabled", 18.0, 18.1)]  # until the operator's reset
    refused = record("erob_impedance_manager/erob/impedance/ring0", 17.0, 27.0)
    assert explained(refused, [lost], faults)
    assert not explained(record("erob_impedance_manager/erob/impedance/ring0", 35.0), [lost], faults)


def test_a_fault_that_must_raise_no_flag_is_not_blamed_for_the_next_injections_flag():
    injection = Injection(ONE_FRAME, at_s=10.0)
    judge(injection, [record("PrimeEtherCATSide/ethercat/wkc", 12.1, 12.5)], ended_s=60.0, next_at_s=12.0)
    assert injection.outcome == "counted"


def test_a_reset_sent_while_the_loop_reads_the_ring_is_judged_to_have_cleared_the_flag_it_cleared(doubled):
    """The reset goes out while the tick that applies it is still reading the ring (a loaded machine's emulator
    answers late), and that tick's write releases the held drive. The flag history stamped the release with the
    tick's start, before the reset was sent, and the judge found a drive re-enabled with no reset sent: 'recovered
    without a reset' in about one soak in four of the full suite."""
    from dataclasses import replace

    from humanoid_prime.bench.soak import Operator

    session = doubled.open(backends="ec")  # no impedance manager: a reset releases a held drive at once
    master, manager = doubled.master, session.manager
    operator = Operator(None, session, threading.Event())
    injection = Injection(replace(LOST, verify=None), at_s=operator.now())
    doubled.power_cycle(LOST_RING)  # the slave came back: its drive is held disabled until a reset
    manager.tick()
    assert f"ethercat/ring{LOST_RING}/disabled" in session.ethercat.flags
    injection.done_s = operator.now()

    asked, request_reset = threading.Event(), manager.request_reset
    manager.request_reset = lambda: (request_reset(), asked.set())[0]
    receive, resetting = master._receive, threading.Thread(target=operator._reset, args=(injection,))

    def receive_while_the_operator_resets() -> int:
        master._receive = receive
        resetting.start()
        assert asked.wait(timeout=60.0)  # sent (and its time kept) before this tick has read the ring
        return receive()

    master._receive = receive_while_the_operator_resets
    manager.tick()
    resetting.join(timeout=60.0)
    assert f"ethercat/ring{LOST_RING}/disabled" not in session.ethercat.flags  # released by this very tick
    judge(injection, session.faults, ended_s=operator.now() + 60.0, resets=operator.resets)
    assert injection.outcome == "latched", (operator.resets, [r.as_dict() for r in session.faults])
