"""Waiting for slaves to change AL state, for as long as the standard lets a state change take, and saying at the
end what each slave that is not there did: refused it (its error indication, with the AL status code), is still
changing (slow, not refused), or does not answer.

How long: the defaults ETG.2000 (§5.3.6.2) gives an ESI's state machine timeouts when a device states none:
PreopTimeout 3 s for INIT -> PRE-OP, SafeopOpTimeout 10 s for PRE-OP -> SAFE-OP and SAFE-OP -> OP,
BackToInitTimeout 5 s for a way down. (SOEM's EC_TIMEOUTSTATE is 2 s, IgH and EtherCrab wait 5 s for any change.) A
slave still below the state it was asked for is asked again every ``ASK_AGAIN_S``: a request whose frame was lost
under load would otherwise never be carried out. The AL status code counts only while the error indication is set
(ETG.1000.6): a slave may leave an old code there after a change that succeeded.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from humanoid_prime.drivers.ethercat.wire import (
    AL_ERROR,
    AL_STATE_MASK,
    AlState,
    describe_al_state,
    describe_al_status_code,
)

PREOP_TIMEOUT_S = 3.0
SAFEOP_OP_TIMEOUT_S = 10.0
BACK_TO_INIT_TIMEOUT_S = 5.0
ASK_AGAIN_S = 0.5
POLL_S = 0.001

StateRead = Sequence[tuple[int, int] | None] | None  # (AL status, AL status code) per slave; None: no answer


def change_timeout(want: int) -> tuple[float, str]:
    """(seconds, the ETG.2000 name) a change to ``want`` may take at most."""
    if want == AlState.PRE_OP:
        return PREOP_TIMEOUT_S, "PreopTimeout"
    if want in (AlState.SAFE_OP, AlState.OP):
        return SAFEOP_OP_TIMEOUT_S, "SafeopOpTimeout"
    return BACK_TO_INIT_TIMEOUT_S, "BackToInitTimeout"


@dataclass(frozen=True)
class StateWait:
    """How a wait for ``want`` ended: each slave's (AL status, AL status code), None where it did not answer."""

    want: int
    states: tuple[tuple[int, int] | None, ...]
    seconds: float

    @property
    def reached(self) -> bool:
        return all(s is not None and s[0] == self.want for s in self.states)

    @property
    def refused(self) -> list[int]:
        """Ring positions that refused (error indication set)."""
        return [k for k, s in enumerate(self.states) if s is not None and s[0] & AL_ERROR]

    def describe(self) -> str:
        """The slaves that are not in ``want``, each with what it did, for an error message."""
        limit, name = change_timeout(self.want)
        want = describe_al_state(self.want)
        parts = []
        for k, state in enumerate(self.states):
            if state is None:
                parts.append(f"ring {k} does not answer")
            elif state[0] & AL_ERROR:
                parts.append(f"ring {k} refused {want}: {describe_al_state(state[0])}, AL status 0x{state[1]:04X} "
                             f"{describe_al_status_code(state[1])}")
            elif state[0] != self.want:
                parts.append(f"ring {k} still in {describe_al_state(state[0])} after {self.seconds:.1f} s, no error "
                             f"indicated (slow, not refused; ETG.2000's {name} is {limit:g} s)")
        return "; ".join(parts) or f"every slave reports {want}"


def await_state(read: Callable[[], StateRead], ask: Callable[[int, int], object], slaves: int, want: int, *,
                clock: Callable[[], float], sleep: Callable[[float], object],
                timeout_s: float | None = None) -> StateWait:
    """Poll ``read()`` until every one of ``slaves`` shows ``want``, one refuses it, or the standard's time for the
    change (``timeout_s`` overrides it) has passed; ``ask(k, want)`` asks slave ``k`` again meanwhile."""
    began = clock()
    deadline = began + (change_timeout(want)[0] if timeout_s is None else timeout_s)
    asked = began
    states: StateRead = None
    while True:
        states = read()
        wait = StateWait(want, tuple(states) if states is not None else (None,) * slaves, clock() - began)
        if states is not None and (wait.reached or wait.refused):
            return wait
        now = clock()
        if now > deadline:
            return wait
        if states is not None and now - asked >= ASK_AGAIN_S:
            asked = now
            for k, state in enumerate(states):
                if state is not None and state[0] & AL_STATE_MASK != want:
                    ask(k, want)
        sleep(POLL_S)
