# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The Sito component's per-tick conversions, compiled: one call turns the latest feedback into joint state,
one call turns the MIT command into the wire's big-endian payloads. As for the eRob (drivers/ethercat/_tick),
the tick's cost had been Python's and NumPy's per-call overhead on four-element arrays.

Every array is the component's own, bound once; the frames themselves are sent by the component."""

from libc.limits cimport INT_MAX, INT_MIN, SHRT_MAX, SHRT_MIN
from libc.math cimport isfinite, isnan, rint
from libc.string cimport memcpy


cdef inline double _clamp(double value, double low, double high) noexcept nogil:
    return low if value < low else high if value > high else value


cdef inline void _put16(unsigned char* at, double value) noexcept nogil:
    cdef unsigned short word = <unsigned short><short>value
    at[0], at[1] = word >> 8, word & 0xFF


cdef inline void _put32(unsigned char* at, unsigned int word) noexcept nogil:
    at[0], at[1], at[2], at[3] = word >> 24, (word >> 16) & 0xFF, (word >> 8) & 0xFF, word & 0xFF


cdef inline void _put_float(unsigned char* at, double value) noexcept nogil:
    cdef float single = <float>value
    cdef unsigned int word
    memcpy(&word, &single, 4)
    _put32(at, word)


cdef class SitoTick:
    """Bound to one SitoSystem's arrays (motor order ``k``; ``index[k]`` is the joint in the robot's arrays).
    Booleans are passed as uint8 views of the component's bool arrays. The payloads are protocol.COMMAND
    (current mA, velocity counts/s, position counts) and protocol.GAINS (kp, kd as float32), big-endian."""

    cdef const Py_ssize_t[::1] index
    cdef const double[:, ::1] to_wire, wire_bias, from_wire, raw, stamp
    cdef const double[::1] state_bias
    cdef unsigned char[::1] late, rx_raised, gains_due
    cdef unsigned char[:, ::1] problems, problems_raised, command_rows, gains_rows
    cdef const unsigned long long[::1] gains_word
    cdef const unsigned long long[::1] gains_sent
    cdef const double[::1] gains_stamp
    cdef double kp_divisor, kd_divisor
    cdef Py_ssize_t n

    def __init__(self, const Py_ssize_t[::1] index not None, const double[:, ::1] to_wire not None,
                 const double[:, ::1] wire_bias not None, const double[:, ::1] from_wire not None,
                 const double[::1] state_bias not None, const double[:, ::1] raw not None,
                 const double[:, ::1] stamp not None, unsigned char[::1] late not None,
                 unsigned char[::1] rx_raised not None, unsigned char[:, ::1] problems not None,
                 unsigned char[:, ::1] problems_raised not None, unsigned char[:, ::1] command_rows not None,
                 unsigned char[:, ::1] gains_rows not None, const unsigned long long[::1] gains_word not None,
                 const unsigned long long[::1] gains_sent not None, const double[::1] gains_stamp not None,
                 unsigned char[::1] gains_due not None, double kp_divisor, double kd_divisor):
        cdef Py_ssize_t n = index.shape[0]
        for name, rows, columns, want_rows, want_columns in (
                ("to_wire", to_wire.shape[0], to_wire.shape[1], 3, n),
                ("wire_bias", wire_bias.shape[0], wire_bias.shape[1], 3, n),
                ("from_wire", from_wire.shape[0], from_wire.shape[1], 3, n),
                ("raw", raw.shape[0], raw.shape[1], 3, n), ("stamp", stamp.shape[0], stamp.shape[1], 2, n),
                ("problems", problems.shape[0], problems.shape[1], 3, n),
                ("problems_raised", problems_raised.shape[0], problems_raised.shape[1], 3, n),
                ("command_rows", command_rows.shape[0], command_rows.shape[1], n, 8),
                ("gains_rows", gains_rows.shape[0], gains_rows.shape[1], n, 8)):
            if rows != want_rows or columns != want_columns:
                raise ValueError(f"{name} is {rows}x{columns}, expected {want_rows}x{want_columns}")
        for name, length in (("state_bias", state_bias.shape[0]), ("late", late.shape[0]),
                             ("rx_raised", rx_raised.shape[0]), ("gains_word", gains_word.shape[0]),
                             ("gains_sent", gains_sent.shape[0]), ("gains_stamp", gains_stamp.shape[0]),
                             ("gains_due", gains_due.shape[0])):
            if length != n:
                raise ValueError(f"{name} has {length} entries for {n} motors")
        self.index, self.to_wire, self.wire_bias, self.from_wire = index, to_wire, wire_bias, from_wire
        self.state_bias, self.raw, self.stamp, self.late, self.rx_raised = state_bias, raw, stamp, late, rx_raised
        self.problems, self.problems_raised = problems, problems_raised
        self.command_rows, self.gains_rows, self.gains_word = command_rows, gains_rows, gains_word
        self.gains_sent, self.gains_stamp, self.gains_due = gains_sent, gains_stamp, gains_due
        self.kp_divisor, self.kd_divisor = kp_divisor, kd_divisor
        self.n = n

    def read(self, double[:, ::1] state not None, double limit):
        """The latest feedback (``raw``: output position counts, velocity counts/s, phase current mA) into
        ``state`` in the joint frame, and which motors have not been heard from since ``limit`` (``late``:
        either feedback frame older). Returns whether ``late`` differs from ``rx_raised``. Call it holding the
        receiver's lock."""
        cdef Py_ssize_t k, j
        cdef double oldest
        cdef bint changed = False
        for k in range(self.n):
            j = self.index[k]
            state[0, j] = self.raw[0, k] * self.from_wire[0, k] - self.state_bias[k]
            state[1, j] = self.raw[1, k] * self.from_wire[1, k]
            state[2, j] = self.raw[2, k] * self.from_wire[2, k]
            oldest = self.stamp[0, k] if self.stamp[0, k] < self.stamp[1, k] else self.stamp[1, k]
            self.late[k] = oldest < limit
            changed |= self.late[k] != self.rx_raised[k]
        return changed

    def write(self, const double[:, ::1] command not None, double due_before):
        """The MIT command (rows position, velocity, effort, stiffness, damping; robot order) into the payloads.

        A motor whose command is not usable (a value not finite, a negative gain) goes limp: zero gains, zero
        effort. That is flagged as an invalid command unless it is "no command" (NaN position, everything else
        zero). Velocity and effort are clamped to their INTEGER16 fields, and flagged where they were. A
        motor's gains are due when they changed since last sent or were last sent at ``due_before`` or
        earlier (``gains_due``). Returns whether ``problems`` (rows velocity clamped, effort clamped, invalid
        command) differs from ``problems_raised``."""
        cdef Py_ssize_t k, j
        cdef double position, velocity, effort, kp, kd, wire, clamped
        cdef bint changed = False
        cdef unsigned char* row
        for k in range(self.n):
            j = self.index[k]
            position, velocity, effort = command[0, j], command[1, j], command[2, j]
            kp, kd = command[3, j], command[4, j]
            if (isfinite(position) and isfinite(velocity) and isfinite(effort) and isfinite(kp) and isfinite(kd)
                    and kp >= 0.0 and kd >= 0.0):
                self.problems[2, k] = False
            else:
                self.problems[2, k] = not (isnan(position) and velocity == 0.0 and effort == 0.0
                                           and kp == 0.0 and kd == 0.0)
                position = velocity = effort = kp = kd = 0.0
            row = &self.command_rows[k, 0]
            wire = rint(effort * self.to_wire[2, k] + self.wire_bias[2, k])
            clamped = _clamp(wire, SHRT_MIN, SHRT_MAX)
            self.problems[1, k] = wire != clamped
            _put16(row, clamped)
            wire = rint(velocity * self.to_wire[1, k] + self.wire_bias[1, k])
            clamped = _clamp(wire, SHRT_MIN, SHRT_MAX)
            self.problems[0, k] = wire != clamped
            _put16(row + 2, clamped)
            wire = rint(position * self.to_wire[0, k] + self.wire_bias[0, k])
            _put32(row + 4, <unsigned int><int>_clamp(wire, INT_MIN, INT_MAX))
            row = &self.gains_rows[k, 0]
            _put_float(row, kp / self.kp_divisor)
            _put_float(row + 4, kd / self.kd_divisor)
            self.gains_due[k] = self.gains_word[k] != self.gains_sent[k] or self.gains_stamp[k] <= due_before
            changed |= (self.problems[0, k] != self.problems_raised[0, k]
                        or self.problems[1, k] != self.problems_raised[1, k]
                        or self.problems[2, k] != self.problems_raised[2, k])
        return changed
