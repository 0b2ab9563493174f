# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The Sito component's per-tick conversions, compiled: one call turns the latest feedback into joint state,
one call turns the MIT command into the wire's payloads. As for the eRob (drivers/ethercat/_tick), the tick's
cost had been Python's and NumPy's per-call overhead on four-element arrays.

The wire format is protocol.py's and is not restated here: the packer is built from its payload layout (a dtype
of big-endian fields) and its table of which field carries each command interface, with the scales the component
derives from protocol's model constants and the calibration. The frames themselves are sent by the component.

The arrays a call is passed (the robot's state and command) and a motor's number are checked at each call against
what the loops will index, so a caller's mistake is a ValueError or an IndexError, never a write past a buffer."""

from libc.math cimport fabs, isfinite, isnan, rint
from libc.string cimport memcmp, memcpy

import numpy as np

cdef enum:
    _INVALID = 5
INVALID = _INVALID  # the row of ``problems`` that says a motor's command was not usable; rows 0 to 4: that interface clamped


cdef struct Field:
    Py_ssize_t offset  # byte of the motor's payloads
    int size  # bytes, big-endian: 2 or 4
    bint real  # an IEEE 754 single, not a two's complement integer
    double low, high  # what the field carries


cdef Field _field(payloads, str payload, str name) except *:
    """Where ``payload``'s field ``name`` lies in a motor's payloads, and what it carries."""
    cdef Field field
    outer, base = payloads.fields[payload][:2]
    kind, offset = outer.fields[name][:2]
    if kind.byteorder != ">" or (kind.kind, kind.itemsize) not in (("i", 2), ("i", 4), ("f", 4)):
        raise ValueError(f"{payload}.{name} is {kind.str}: the packer writes big-endian int16, int32 and float32")
    limits = np.finfo(kind) if kind.kind == "f" else np.iinfo(kind)
    field.offset, field.size, field.real = base + offset, kind.itemsize, kind.kind == "f"
    field.low, field.high = float(limits.min), float(limits.max)
    return field


cdef inline void _put(unsigned char* at, Field field, double value) noexcept nogil:
    cdef float single
    cdef unsigned int word
    cdef int byte
    if field.real:
        single = <float>value
        memcpy(&word, &single, 4)
    elif field.size == 4:
        word = <unsigned int><int>value
    else:
        word = <unsigned short><short>value
    for byte in range(field.size):
        at[field.offset + byte] = (word >> (8 * (field.size - 1 - byte))) & 0xFF


cdef inline int _fits(str name, Py_ssize_t rows_have, Py_ssize_t columns_have, Py_ssize_t rows,
                      Py_ssize_t columns) except -1:
    """Raise unless an array of ``rows_have`` x ``columns_have`` has the ``rows`` x ``columns`` a loop indexes."""
    if rows_have < rows or columns_have < columns:
        raise ValueError(f"{name} is {rows_have}x{columns_have}, needs at least {rows}x{columns}")
    return 0


cdef class SitoTick:
    """Bound to one SitoSystem's feedback arrays (motor order ``k``; ``index[k]`` is the joint in the robot's
    arrays). ``to_wire`` (5 x n) is wire units per joint-frame unit of each command interface (direction and
    protocol scale), ``wire_bias`` (n) the position offset in counts; the state is read with their inverse.

    It owns, as NumPy arrays: ``payloads`` (n motors' ``payload_dtype``), ``late`` and ``rx_raised`` (n),
    ``problems`` and ``problems_raised`` (6 x n: rows 0 to 4 an interface sent clamped, row ``INVALID`` a command
    not usable) and ``gains_due`` (n)."""

    cdef Field fields[5]
    cdef Py_ssize_t gains_offset, gains_size, n, columns  # columns the robot's arrays need: highest index, plus 1
    cdef const Py_ssize_t[::1] index
    cdef const double[:, ::1] to_wire, raw, stamp
    cdef const double[::1] wire_bias
    cdef double[:, ::1] from_wire
    cdef unsigned char[:, ::1] wire, gains_sent
    cdef unsigned char[::1] late_, rx_raised_, gains_due_
    cdef unsigned char[:, ::1] problems_, problems_raised_
    cdef double[::1] gains_stamp
    cdef readonly object payloads, late, rx_raised, problems, problems_raised, gains_due

    def __init__(self, const Py_ssize_t[::1] index not None, const double[:, ::1] to_wire not None,
                 const double[::1] wire_bias not None, const double[:, ::1] raw not None,
                 const double[:, ::1] stamp not None, payload_dtype, tuple mit_fields):
        cdef Py_ssize_t n = index.shape[0], r, k, needed = 0
        for k in range(n):
            if index[k] < 0:
                raise ValueError(f"index[{k}] is {index[k]}: a joint is a column of the robot's arrays, 0 or more")
            needed = max(needed, index[k] + 1)
        for name, rows, columns, want in (("to_wire", to_wire.shape[0], to_wire.shape[1], 5),
                                          ("raw", raw.shape[0], raw.shape[1], 3),
                                          ("stamp", stamp.shape[0], stamp.shape[1], 2)):
            if rows != want or columns != n:
                raise ValueError(f"{name} is {rows}x{columns}, expected {want}x{n}")
        if wire_bias.shape[0] != n:
            raise ValueError(f"wire_bias has {wire_bias.shape[0]} entries for {n} motors")
        if len(mit_fields) != 5 or mit_fields[3][0] != mit_fields[4][0]:
            raise ValueError("mit_fields names the field of each of the five command interfaces, both gains in "
                             "one payload")
        for r in range(5):
            payload, name = mit_fields[r]
            self.fields[r] = _field(payload_dtype, payload, name)
        gains, self.gains_offset = payload_dtype.fields[mit_fields[3][0]][:2]  # the payload the gains travel in
        self.gains_size = gains.itemsize
        self.index, self.to_wire, self.wire_bias, self.raw, self.stamp = index, to_wire, wire_bias, raw, stamp
        self.from_wire = 1.0 / np.asarray(to_wire)[:3]
        self.n, self.columns = n, needed
        self.payloads = np.zeros(n, dtype=payload_dtype)
        self.wire = self.payloads.view(np.uint8).reshape(n, payload_dtype.itemsize)
        self.gains_sent = np.zeros((n, self.gains_size), dtype=np.uint8)
        self.gains_stamp = np.zeros(n)
        self.late, self.rx_raised, self.gains_due = (np.zeros(n, dtype=bool) for _ in range(3))
        self.problems, self.problems_raised = np.zeros((6, n), dtype=bool), np.zeros((6, n), dtype=bool)
        self.late_, self.rx_raised_, self.gains_due_ = (a.view(np.uint8) for a in (self.late, self.rx_raised,
                                                                                   self.gains_due))
        self.problems_, self.problems_raised_ = self.problems.view(np.uint8), self.problems_raised.view(np.uint8)

    def gains_sent_at(self, Py_ssize_t k, double now):
        """Motor ``k``'s gains payload went out at ``now``: it is due again when it changes or goes stale."""
        if not 0 <= k < self.n:
            raise IndexError(f"no motor {k}: there are {self.n}")
        memcpy(&self.gains_sent[k, 0], &self.wire[k, self.gains_offset], self.gains_size)
        self.gains_stamp[k] = now

    def read(self, double[:, ::1] state not None, double limit):
        """The latest feedback (``raw``: output position counts, velocity counts/s, phase current mA) into
        ``state`` in the joint frame, and which motors have not been heard from since ``limit`` (``late``:
        either feedback frame older). Returns whether ``late`` differs from ``rx_raised``. Call it holding the
        receiver's lock."""
        cdef Py_ssize_t k, j
        cdef double oldest
        cdef bint changed = False
        _fits("state", state.shape[0], state.shape[1], 3, self.columns)
        for k in range(self.n):
            j = self.index[k]
            state[0, j] = (self.raw[0, k] - self.wire_bias[k]) * self.from_wire[0, k]
            state[1, j] = self.raw[1, k] * self.from_wire[1, k]
            state[2, j] = self.raw[2, k] * self.from_wire[2, k]
            oldest = self.stamp[0, k] if self.stamp[0, k] < self.stamp[1, k] else self.stamp[1, k]
            self.late_[k] = oldest < limit
            changed |= self.late_[k] != self.rx_raised_[k]
        return changed

    def write(self, const double[:, ::1] command not None, double due_before):
        """The MIT command (rows position, velocity, effort, stiffness, damping; robot order) into the payloads.

        A motor whose command is not usable (a value not finite, a negative gain, a gain its field cannot carry)
        goes limp: zero gains, zero effort. That is flagged (row ``INVALID``) unless it is "no command" (NaN
        position, everything else zero). An integer field saturates at its type's range, flagged in the row of
        its interface. A motor's gains are due when they changed since last sent or were last sent at
        ``due_before`` or earlier. Returns whether ``problems`` differs from ``problems_raised``."""
        cdef Py_ssize_t k, j, r
        cdef double value[5]
        cdef double wire[5]
        cdef double clamped
        cdef bint usable, changed = False
        cdef unsigned char* at
        cdef Field field
        _fits("command", command.shape[0], command.shape[1], 5, self.columns)
        for k in range(self.n):
            j = self.index[k]
            usable = command[3, j] >= 0.0 and command[4, j] >= 0.0
            for r in range(5):
                value[r] = command[r, j]
                usable = usable and isfinite(value[r])
                wire[r] = value[r] * self.to_wire[r, k]
            wire[0] += self.wire_bias[k]
            for r in range(5):
                if self.fields[r].real and not fabs(wire[r]) <= self.fields[r].high:
                    usable = False
            if usable:
                self.problems_[_INVALID, k] = False
            else:
                self.problems_[_INVALID, k] = not (isnan(value[0]) and value[1] == 0.0 and value[2] == 0.0
                                                  and value[3] == 0.0 and value[4] == 0.0)
                for r in range(5):
                    wire[r] = 0.0
                wire[0] = self.wire_bias[k]
            at = &self.wire[k, 0]
            for r in range(5):
                field = self.fields[r]
                if not field.real:
                    wire[r] = rint(wire[r])
                    clamped = field.low if wire[r] < field.low else field.high if wire[r] > field.high else wire[r]
                    self.problems_[r, k] = clamped != wire[r]
                    wire[r] = clamped
                _put(at, field, wire[r])
            self.gains_due_[k] = (self.gains_stamp[k] <= due_before
                                  or memcmp(&self.gains_sent[k, 0], at + self.gains_offset, self.gains_size) != 0)
            for r in range(6):
                changed |= self.problems_[r, k] != self.problems_raised_[r, k]
        return changed
