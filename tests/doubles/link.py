"""The link's wire, in-process and on emulated time: frames go through an emulated ``Ring`` at once, and their
replies come back when the test says: at once, held back by some time, or never (lost).

``RingHub`` is one segment of cable: each ``port(indices)`` is what one channel's socket would see (only replies
with its indices). Time moves only when a port waits (``receive``) or somebody sleeps on the ``clock``; the ring
is advanced with it, a millisecond at a time, so the drives' mailbox replies come after their emulated latency,
and ``cycle`` (when set) sends the master's cyclic frame at each of those milliseconds, as its keeper would while
a test waits.
"""

from __future__ import annotations

import heapq
import itertools
import threading
from collections.abc import Callable, Sequence

from humanoid_prime.drivers.ethercat.link import frame_index
from humanoid_prime.virtual.ring.ring import Ring


class EmulatedClock:
    """Seconds that move only when a wire waits or a caller sleeps (one thread at a time: ``lock``)."""

    def __init__(self, now: float = 1000.0) -> None:
        self.now = now
        self.on_advance: Callable[[float], None] | None = None
        self.lock = threading.RLock()

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.advance_to(self.now + max(seconds, 0.0))

    def advance_to(self, when: float) -> None:
        with self.lock:
            if when > self.now:
                self.now = when
                if self.on_advance is not None:
                    self.on_advance(when)


class RingHub:
    """Frames through ``ring`` on ``clock``; scripted losses and holds act on the next frames that match."""

    STEP_S = 0.001

    def __init__(self, ring: Ring, clock: EmulatedClock) -> None:
        self.ring = ring
        self.clock = clock
        self.cycle: Callable[[], None] | None = None
        self._advanced = clock.now
        clock.on_advance = self._advance
        self.sent: list[bytes] = []  # every frame sent, as sent
        self._stalled_until = 0.0
        self._queue: list[tuple[float, int, bytes]] = []  # (due, order, reply)
        self._order = itertools.count()
        self._lose: list[Callable[[bytes, bool], bool]] = []
        self._hold: list[tuple[Callable[[bytes, bool], bool], float]] = []
        self._until_reuse: list[Callable[[bytes, bool], bool]] = []
        self._held_for_reuse: list[bytes] = []
        self.released_on_reuse = 0
        self._lock = clock.lock  # the ring is one: frames and time through it one at a time

    def _advance(self, now: float) -> None:
        while self._advanced + self.STEP_S <= now:
            self._advanced += self.STEP_S
            self.ring.advance(round(self._advanced * 1e9))
            if self.cycle is not None:
                self.cycle()
        self.ring.advance(round(now * 1e9))

    # ---- what the test scripts ----------------------------------------------------------------------------
    def stall(self, seconds: float) -> None:
        """From now on for ``seconds``, every reply comes back only then (a host that did not run the ring)."""
        self._stalled_until = self.clock.now + seconds

    def lose_next(self, when: Callable[[bytes, bool], bool] = lambda frame, took_reply: True) -> None:
        """The next reply frame for which ``when(frame, took_reply)`` holds never comes back (the slaves acted
        on it). ``took_reply``: the frame took a mailbox reply out of a slave."""
        self._lose.append(when)

    def hold_next(self, seconds: float, when: Callable[[bytes, bool], bool] = lambda frame, took_reply: True) -> None:
        """The next reply frame for which ``when`` holds comes back ``seconds`` late."""
        self._hold.append((when, seconds))

    def hold_until_reuse(self, when: Callable[[bytes, bool], bool]) -> None:
        """The next reply frame for which ``when`` holds comes back late, exactly when its datagram index is used
        again (just before that frame's own reply): the worst moment for a master that files by index."""
        self._until_reuse.append(when)

    # ---- the wire -----------------------------------------------------------------------------------------
    def send(self, frame: bytes) -> None:
        with self._lock:
            self.sent.append(bytes(frame))
            index = frame_index(frame)
            for held in [h for h in self._held_for_reuse if frame_index(h) == index]:
                self._held_for_reuse.remove(held)
                self.released_on_reuse += 1
                heapq.heappush(self._queue, (self.clock.now, next(self._order), held))
            taken = sum(slave.replies_taken for slave in self.ring.slaves)
            reply = bytearray(frame)
            self.ring.process(reply, round(self.clock.now * 1e9))
            self.ring.finish_frame()
            took_reply = sum(slave.replies_taken for slave in self.ring.slaves) != taken
            for k, when in enumerate(self._lose):
                if when(bytes(reply), took_reply):
                    del self._lose[k]
                    return
            for k, when in enumerate(self._until_reuse):
                if when(bytes(reply), took_reply):
                    del self._until_reuse[k]
                    self._held_for_reuse.append(bytes(reply))
                    return
            delay = max(self._stalled_until - self.clock.now, 0.0)
            for k, (when, seconds) in enumerate(self._hold):
                if when(bytes(reply), took_reply):
                    del self._hold[k]
                    delay = seconds
                    break
            heapq.heappush(self._queue, (self.clock.now + delay, next(self._order), bytes(reply)))

    def port(self, indices: Sequence[int]) -> HubPort:
        return HubPort(self, set(indices))

    def watch(self) -> HubWatch:
        """What a packet socket that only looks would see: the frames sent through the hub from now on."""
        return HubWatch(self)

    def _take(self, indices: set[int], timeout_s: float) -> bytes | None:
        with self._lock:
            mine = [item for item in self._queue if frame_index(item[2]) in indices]
            limit = self.clock.now + max(timeout_s, 1e-6)  # time always moves on (a float step can vanish at 1e3 s)
            if not mine or min(mine)[0] > limit:
                self.clock.advance_to(limit)
                return None
            item = min(mine)
            self._queue.remove(item)
            heapq.heapify(self._queue)
            self.clock.advance_to(item[0])
            return item[2]


class HubWatch:
    def __init__(self, hub: RingHub) -> None:
        self.hub = hub
        self._seen = len(hub.sent)

    def indices(self) -> list[int]:
        frames, self._seen = self.hub.sent[self._seen:], len(self.hub.sent)
        return [index for index in map(frame_index, frames) if index is not None]

    def close(self) -> None:
        pass


class HubPort:
    def __init__(self, hub: RingHub, indices: set[int]) -> None:
        self.hub = hub
        self.indices = indices

    def send(self, frame: bytes) -> None:
        self.hub.send(frame)

    def receive(self, timeout_s: float) -> bytes | None:
        return self.hub._take(self.indices, timeout_s)

    def close(self) -> None:
        pass
