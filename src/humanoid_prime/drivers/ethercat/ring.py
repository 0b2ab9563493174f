"""What a ring holds: the slaves the hardware file expects and the slaves found, and the check of one against the
other (identity and ring position of every slave)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from humanoid_prime.drivers.erob.constants import PRODUCT_CODE, VENDOR_ID
from humanoid_prime.drivers.ethercat.errors import RingError
from humanoid_prime.drivers.ethercat.wire import AL_ERROR, describe_al_state, describe_al_status_code

HARDWARE_KEY = "prime_hardware.yaml joints.erob_slaves"


@dataclass(frozen=True)
class ExpectedSlave:
    """What the hardware file says sits at one ring position."""

    position: int
    joint: str
    vendor_id: int = VENDOR_ID
    product_code: int = PRODUCT_CODE

    @property
    def identity(self) -> str:
        return _identity(self.vendor_id, self.product_code)


@dataclass(frozen=True)
class SlaveInfo:
    """One slave as found on the ring: identity from its SII, AL state and AL status code."""

    position: int
    name: str
    vendor_id: int
    product_code: int
    revision: int = 0
    al_state: int = 0
    al_status_code: int = 0

    @property
    def identity(self) -> str:
        return _identity(self.vendor_id, self.product_code)

    @property
    def is_erob(self) -> bool:
        return self.vendor_id == VENDOR_ID and self.product_code == PRODUCT_CODE

    @property
    def state_text(self) -> str:
        return describe_al_state(self.al_state)

    def describe(self) -> str:
        text = f"'{self.name}' ({self.identity})" if self.name else self.identity
        return text


def _identity(vendor_id: int, product_code: int) -> str:
    kind = "eRob " if (vendor_id, product_code) == (VENDOR_ID, PRODUCT_CODE) else ""
    return f"{kind}vendor 0x{vendor_id:08X} product 0x{product_code:08X}"


def describe_states(slaves: Sequence[SlaveInfo], want: int) -> str:
    """The slaves not in AL state ``want``, with their state and AL status code, for an error message."""
    parts = []
    for slave in slaves:
        if slave.al_state != want:
            text = f"ring {slave.position} {slave.state_text}"
            if slave.al_state & AL_ERROR and slave.al_status_code:  # a code counts with its error indication only
                code = slave.al_status_code
                text += f" (AL status 0x{code:04X} {describe_al_status_code(code)})"
            parts.append(text)
    return "; ".join(parts) or f"every slave reports {describe_al_state(want)}"


def expected_ring(erob_slaves: Mapping[str, int]) -> tuple[ExpectedSlave, ...]:
    """The expected ring of a hardware file's ``joints.erob_slaves`` (joint -> ring position), by position."""
    return tuple(sorted((ExpectedSlave(pos, joint) for joint, pos in erob_slaves.items()), key=lambda e: e.position))


def check_ring(found: Sequence[SlaveInfo], expected: Sequence[ExpectedSlave], interface: str) -> None:
    """Raise one RingError listing found versus expected unless every ring position holds the expected slave."""
    by_position = {e.position: e for e in expected}
    problems = []
    if len(found) != len(expected):
        problems.append(f"found {len(found)} slaves, expected {len(expected)}")
    for position in sorted(set(by_position) | {s.position for s in found}):
        want = by_position.get(position)
        have = found[position] if position < len(found) else None
        if want is None and have is not None:
            problems.append(f"ring {position}: found {have.describe()}, expected no slave")
        elif want is not None and have is None:
            problems.append(f"ring {position}: expected {want.joint} ({want.identity}), found nothing")
        elif want is not None and have is not None and (have.vendor_id, have.product_code) != (
                want.vendor_id, want.product_code):
            problems.append(f"ring {position}: expected {want.joint} ({want.identity}), found {have.describe()}")
    if problems:
        runs: list[tuple[int, int, str]] = []  # consecutive positions holding the same device, e.g. "0-8 'eRob' (...)"
        for slave in found:
            if runs and runs[-1][2] == slave.describe():
                runs[-1] = (runs[-1][0], slave.position, runs[-1][2])
            else:
                runs.append((slave.position, slave.position, slave.describe()))
        seen = ", ".join(f"{a}-{b} {what}" if b > a else f"{a} {what}" for a, b, what in runs) or "none"
        raise RingError(f"EtherCAT ring on {interface} does not match {HARDWARE_KEY}: " + "; ".join(problems)
                        + f" (found ring: {seen}); fix the cabling order or the ring positions in the hardware file")
