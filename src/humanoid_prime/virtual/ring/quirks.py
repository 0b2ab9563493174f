"""What real slaves do that the specification allows, or that a master meets anyway: switchable profiles of the
emulated eRob, so a master is tested against the peers it will meet and not only against this emulator's manners.

``prime emulate ec --quirks NAME,...``, ``--emulate --quirks NAME,...`` and ``RingOptions(quirks=...)`` switch them
on; ``all`` is every profile at once. docs/hardware.md has the table of where each is seen and what Prime does.
"""

from __future__ import annotations

from dataclasses import dataclass

# name -> what the slave does, where it is seen
PROFILES: dict[str, str] = {
    "reserved-bits": "SDO replies carry the request's low bits where the specification reserves them (0x2F -> 0x6F, "
                     "0x23 -> 0x63), aborts too (0x2F -> 0x8F): KickCAT's slave stack answers in the request's own "
                     "buffer and rewrites only the command specifier (lib/src/CoE/mailbox/response.cc)",
    "counter": "the mailbox counter of its replies is its own: it starts anywhere, never echoes the request's "
               "(EtherCrab #236: a request with counter 1 answered with 2) and moves on only every other reply; and a "
               "request that repeats the last one's counter is served again (a slave stack that does not check it)",
    "no-size": "expedited uploads of 4-byte values without a size indication (e = 1, s = 0), which CiA 301 allows "
               "and canopen-python #395 and lely-core #1 met (a shorter value so sent breaks SOEM's read-back of the "
               "PDO mapping into 1- and 2-byte buffers, so it is left out here; Prime's layer takes it too)",
    "normal-upload": "4-byte values answered as normal (not expedited) uploads, the size u32 before the data",
    "slow-sii": "an EEPROM that stays busy for milliseconds per read (SOEM #92: a 24LC16B)",
    "slow-states": "state changes that take their time (ZeroErr's eRob_SOEM_linux #19, SOEM #355: eRob slow to PRE-OP "
                   "after power-up; SOES #204), the first OP request refused until its SYNC0 runs, and AL status codes "
                   "left set after the change succeeded (ETG.1000.6 lets the master ignore them, KickCAT #139)",
    "emergency": "CoE emergency messages in the mailbox between replies (SOEM #970: a Beckhoff AX8206 during SDO "
                 "reads)",
    "abort-service": "aborts sent under the SDO response service instead of the request service (SOES #115)",
}
ALL = "all"
SLOW_SII_S = 0.003  # per EEPROM read: within SOEM's 20 ms EC_TIMEOUTEEP and EtherCrab's 10 ms
SLOW_STATE_S = 0.6  # per state change: within ETG.2000's PreopTimeout (3 s) and SafeopOpTimeout (10 s)
EMERGENCY_EVERY = 3  # an emergency ahead of every third reply


@dataclass(frozen=True)
class Quirks:
    """The profiles a slave has, by name (``PROFILES``)."""

    names: frozenset[str] = frozenset()

    @classmethod
    def parse(cls, text: str) -> Quirks:
        """From ``a,b`` or ``all`` (ValueError names an unknown profile and the known ones)."""
        names = {name.strip() for name in text.split(",") if name.strip()}
        if ALL in names:
            return cls(frozenset(PROFILES))
        unknown = sorted(names - set(PROFILES))
        if unknown:
            raise ValueError(f"unknown quirk profile {unknown[0]!r}; known: {', '.join(PROFILES)}, or {ALL}")
        return cls(frozenset(names))

    def __contains__(self, name: str) -> bool:
        return name in self.names

    def __str__(self) -> str:
        return ",".join(name for name in PROFILES if name in self.names)


NO_QUIRKS = Quirks()
