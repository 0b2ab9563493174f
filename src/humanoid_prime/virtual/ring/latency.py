"""How long the emulated drives take to answer a mailbox request: the ring's one latency model.

A real eRob answers an SDO within a fraction of a millisecond, but not always: its firmware may be busy, and a
busy host running a simulator stalls for tens of milliseconds. The model adds to ``mailbox_latency_s``:

- jitter: up to ``mailbox_jitter_s`` more, uniformly at random, on every reply;
- bursts: with ``mailbox_burst_chance`` a reply starts a burst, and it and the next ``mailbox_burst_replies - 1``
  replies (of any slave) come ``mailbox_burst_s`` later;
- scripted delays (``script``): the next replies of one slave, or of any, come a given time later, to put a reply
  exactly past a master's timeout.

Draws come from one generator seeded with ``seed``, so a run with the same frames is the same run.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

from humanoid_prime.virtual.ring.options import RingOptions


@dataclass
class _Scripted:
    count: int
    delay_ns: int
    position: int | None


class MailboxLatency:
    """Shared by the slaves of one ring (a burst, like a stalled host, slows every slave's replies)."""

    def __init__(self, options: RingOptions) -> None:
        self.options = options
        self._random = random.Random(options.seed)
        self._burst_left = 0
        self._scripted: list[_Scripted] = []
        self.slowed = 0  # replies that came later than mailbox_latency_s, for the control channel's status

    def script(self, count: int, seconds: float, position: int | None = None) -> None:
        """The next ``count`` replies (of ring ``position``, or of any slave) come ``seconds`` later."""
        if count < 0 or not 0 <= seconds < 10:
            raise ValueError(f"late replies need count >= 0 and 0 <= seconds < 10, got {count} and {seconds}")
        self._scripted.append(_Scripted(count, round(seconds * 1e9), position))

    def delay_ns(self, position: int) -> int:
        """Time from a request of ring ``position`` to its reply, for the reply being queued now."""
        options = self.options
        extra = 0
        if options.mailbox_jitter_s:
            extra += round(self._random.uniform(0.0, options.mailbox_jitter_s) * 1e9)
        if not self._burst_left and options.mailbox_burst_chance and \
                self._random.random() < options.mailbox_burst_chance:
            self._burst_left = options.mailbox_burst_replies
        if self._burst_left:
            self._burst_left -= 1
            extra += round(options.mailbox_burst_s * 1e9)
        for scripted in self._scripted:
            if scripted.count and scripted.position in (None, position):
                scripted.count -= 1
                extra += scripted.delay_ns
                break
        self._scripted = [s for s in self._scripted if s.count]
        if extra:
            self.slowed += 1
        return round(options.mailbox_latency_s * 1e9) + extra
