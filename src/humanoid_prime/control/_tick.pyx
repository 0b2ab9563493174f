# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The per-tick work around the controllers, compiled:

- ``OutputCheck``: the manager's copy of the last command into the proposal, the output check with its clip,
  and the copy of the checked proposal back into the command. The kernel only decides; the manager words the
  problem from ``row`` and ``col``.
- ``Copy``, ``FollowMeasured``, ``Blend``: the joint-state broadcaster's copy and the commands of the three
  built-in modes (DAMPING, ZERO_TORQUE, STANDBY), which are also the fallback chain.

In NumPy the output check alone was a dozen calls on 14-element arrays, about 100 us a tick at 50 Hz, when the
interpreter's and NumPy's code paths have left the caches between ticks; a bound kernel call is a few tens of
nanoseconds warm. The policy controllers stay Python, around onnxruntime."""

from libc.math cimport isfinite
from libc.string cimport memcpy

import numpy as np

# What check() found; the manager has the words for each.
OK = 0
NON_FINITE = 1  # at (row, col), the first in row-major order
NEGATIVE_GAIN = 2  # stiffness (row 3) or damping (row 4): the most negative of that row, first if tied
EFFORT = 3  # the first joint whose |effort| is beyond its limit
BELOW = 4  # the first stiff joint whose target is further than the margin below its lower limit
ABOVE = 5  # likewise above the upper limit


cdef class OutputCheck:
    """Bound to the manager's proposal and command arrays (5 x n, C order) and the joints' limits."""

    cdef double[:, ::1] proposal, command
    cdef const double[::1] lower, upper, effort_limit
    cdef double margin
    cdef Py_ssize_t n
    cdef readonly Py_ssize_t row, col

    def __init__(self, double[:, ::1] proposal not None, double[:, ::1] command not None,
                 const double[::1] lower not None, const double[::1] upper not None,
                 const double[::1] effort_limit not None, double margin):
        cdef Py_ssize_t n = proposal.shape[1]
        if proposal.shape[0] != 5 or command.shape[0] != 5 or command.shape[1] != n:
            raise ValueError(f"proposal and command must both be 5 x {n}")
        if lower.shape[0] != n or upper.shape[0] != n or effort_limit.shape[0] != n:
            raise ValueError(f"the limits must have {n} joints")
        self.proposal, self.command = proposal, command
        self.lower, self.upper, self.effort_limit = lower, upper, effort_limit
        self.margin = margin
        self.n = n
        self.row = self.col = -1

    def propose(self):
        """The proposal starts as the last command (a controller that skips a row leaves it as it was)."""
        memcpy(&self.proposal[0, 0], &self.command[0, 0], 5 * self.n * sizeof(double))

    def commit(self):
        memcpy(&self.command[0, 0], &self.proposal[0, 0], 5 * self.n * sizeof(double))

    def check(self):
        """The manager's output check on the proposal; a target within the margin of a limit is clipped onto
        it in place. Returns OK or what was found, with ``row`` and ``col`` saying where."""
        cdef double[:, ::1] data = self.proposal
        cdef Py_ssize_t n = self.n, r, j, worst
        cdef double value, target
        if n == 0:
            return OK
        for r in range(5):
            for j in range(n):
                if not isfinite(data[r, j]):
                    return self._found(NON_FINITE, r, j)
        for r in (3, 4):
            worst = 0
            for j in range(1, n):
                if data[r, j] < data[r, worst]:
                    worst = j
            if data[r, worst] < 0.0:
                return self._found(NEGATIVE_GAIN, r, worst)
        for j in range(n):
            value = data[2, j]
            if (value if value >= 0.0 else -value) > self.effort_limit[j]:
                return self._found(EFFORT, 2, j)
        for j in range(n):
            if data[3, j] > 0.0 and data[0, j] < self.lower[j] - self.margin:
                return self._found(BELOW, 0, j)
        for j in range(n):
            if data[3, j] > 0.0 and data[0, j] > self.upper[j] + self.margin:
                return self._found(ABOVE, 0, j)
        for j in range(n):
            if data[3, j] > 0.0:
                target = data[0, j]
                data[0, j] = self.lower[j] if target < self.lower[j] else self.upper[j] if target > self.upper[j] \
                    else target
        self.row = self.col = -1
        return OK

    cdef int _found(self, int kind, Py_ssize_t row, Py_ssize_t col):
        self.row, self.col = row, col
        return kind


cdef class Copy:
    """``run(dst, src)``: dst[...] = src for two C-contiguous float64 arrays of one shape. The views are bound
    on the first call and again only when another array is passed, so a tick that passes the same arrays pays
    one memcpy, not NumPy's dispatch."""

    cdef object _dst, _src
    cdef double[::1] dst
    cdef const double[::1] src

    def run(self, dst, src):
        if dst is not self._dst or src is not self._src:
            self._bind(dst, src)
        memcpy(&self.dst[0], &self.src[0], self.dst.shape[0] * sizeof(double))

    cdef _bind(self, dst, src):
        if dst.shape != src.shape or not dst.size:
            raise ValueError(f"cannot copy an array of shape {src.shape} into one of shape {dst.shape}")
        if not (dst.flags.c_contiguous and src.flags.c_contiguous):
            raise ValueError("both arrays must be C-contiguous")
        self.dst, self.src = dst.reshape(-1), src.reshape(-1)  # views: both are contiguous
        self._dst, self._src = dst, src


cdef class FollowMeasured:
    """ZERO_TORQUE's command, ``run(position, command)``: the position target follows the measured position
    where that is finite (elsewhere it keeps the last target), and the other four rows are zero. Bound like
    ``Copy``."""

    cdef object _position, _command
    cdef const double[::1] position
    cdef double[:, ::1] command

    def run(self, position, command):
        if position is not self._position or command is not self._command:
            self._bind(position, command)
        cdef Py_ssize_t j, n = self.command.shape[1]
        cdef double[:, ::1] out = self.command
        for j in range(n):
            if isfinite(self.position[j]):
                out[0, j] = self.position[j]
            out[1, j] = out[2, j] = out[3, j] = out[4, j] = 0.0

    cdef _bind(self, position, command):
        cdef const double[::1] p = position
        cdef double[:, ::1] c = command
        if c.shape[0] != 5 or p.shape[0] != c.shape[1]:
            raise ValueError(f"need a 5 x {p.shape[0]} command for {p.shape[0]} positions")
        self.position, self.command = p, c
        self._position, self._command = position, command


cdef class Blend:
    """STANDBY's command, ``run(start, delta, blend, speed, kp, kd, command)``: position start + blend * delta,
    velocity speed * delta, no effort, stiffness kp, damping kd. Bound like ``Copy``."""

    cdef object _start, _delta, _command
    cdef const double[::1] start, delta
    cdef double[:, ::1] command

    def run(self, start, delta, double blend, double speed, double kp, double kd, command):
        if start is not self._start or delta is not self._delta or command is not self._command:
            self._bind(start, delta, command)
        cdef Py_ssize_t j, n = self.command.shape[1]
        cdef double[:, ::1] out = self.command
        for j in range(n):
            out[0, j] = self.start[j] + blend * self.delta[j]
            out[1, j] = speed * self.delta[j]
            out[2, j] = 0.0
            out[3, j] = kp
            out[4, j] = kd

    cdef _bind(self, start, delta, command):
        cdef const double[::1] s = start, d = delta
        cdef double[:, ::1] c = command
        if c.shape[0] != 5 or s.shape[0] != c.shape[1] or d.shape[0] != c.shape[1]:
            raise ValueError(f"need a 5 x {s.shape[0]} command for {s.shape[0]} joints")
        self.start, self.delta, self.command = s, d, c
        self._start, self._delta, self._command = start, delta, command


cdef class CommandCheck:
    """REMOTE's check of an incoming command, ``take(position, velocity, effort, stiffness, damping)``: True after
    copying the five rows into the bound inbox (5 x n) when every value is finite, no stiffness or damping is
    negative, no effort is beyond its joint's limit and no stiff target lies outside ``[lower, upper]`` (stiff:
    ``fixed_kp`` > 0 on the joints ``fixed`` marks, the message's stiffness elsewhere); False, the inbox
    untouched, when any check fails or a row is not n numbers. A command arrives every tick, from the publisher's
    thread (DDS's on the robot): as NumPy calls the same checks were about 15 us a message."""

    cdef double[:, ::1] inbox
    cdef const double[::1] lower, upper, effort_limit, fixed_kp
    cdef const unsigned char[::1] fixed
    cdef Py_ssize_t n

    def __init__(self, double[:, ::1] inbox not None, const double[::1] lower not None,
                 const double[::1] upper not None, const double[::1] effort_limit not None,
                 const unsigned char[::1] fixed not None, const double[::1] fixed_kp not None):
        cdef Py_ssize_t n = inbox.shape[1]
        if inbox.shape[0] != 5:
            raise ValueError(f"the inbox must be 5 x {n}")
        if (lower.shape[0] != n or upper.shape[0] != n or effort_limit.shape[0] != n or fixed.shape[0] != n
                or fixed_kp.shape[0] != n):
            raise ValueError(f"the limits must have {n} joints")
        self.inbox = inbox
        self.lower, self.upper, self.effort_limit = lower, upper, effort_limit
        self.fixed, self.fixed_kp = fixed, fixed_kp
        self.n = n

    def take(self, position, velocity, effort, stiffness, damping):
        cdef const double[::1] p, v, e, s, d
        cdef Py_ssize_t j, n = self.n
        cdef double kp
        try:
            p = _row(position)
            v = _row(velocity)
            e = _row(effort)
            s = _row(stiffness)
            d = _row(damping)
        except (TypeError, ValueError, BufferError):
            return False
        if p.shape[0] != n or v.shape[0] != n or e.shape[0] != n or s.shape[0] != n or d.shape[0] != n:
            return False
        for j in range(n):
            if not (isfinite(p[j]) and isfinite(v[j]) and isfinite(e[j]) and isfinite(s[j]) and isfinite(d[j])):
                return False
            if s[j] < 0.0 or d[j] < 0.0 or (e[j] if e[j] >= 0.0 else -e[j]) > self.effort_limit[j]:
                return False
            kp = self.fixed_kp[j] if self.fixed[j] else s[j]
            if kp > 0.0 and (p[j] < self.lower[j] or p[j] > self.upper[j]):
                return False
        if n:
            memcpy(&self.inbox[0, 0], &p[0], n * sizeof(double))
            memcpy(&self.inbox[1, 0], &v[0], n * sizeof(double))
            memcpy(&self.inbox[2, 0], &e[0], n * sizeof(double))
            memcpy(&self.inbox[3, 0], &s[0], n * sizeof(double))
            memcpy(&self.inbox[4, 0], &d[0], n * sizeof(double))
        return True


cdef const double[::1] _row(values):
    """``values`` as a C-contiguous float64 vector, without a copy when it already is one."""
    cdef const double[::1] row
    if isinstance(values, np.ndarray) and values.dtype == np.float64 and values.flags.c_contiguous:
        row = values
    else:
        row = np.ascontiguousarray(values, dtype=np.float64)
    return row
