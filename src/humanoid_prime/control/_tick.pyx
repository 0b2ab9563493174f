# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The per-tick work around the controllers, compiled:

- ``CommandCheck``: the bounds every command meets before it reaches a bus (control/bounds.py has the rules in
  words), applied by ``OutputCheck`` to the manager's proposal every tick and by ``Inbox`` to each REMOTE message
  as it arrives. The kernel only decides; ``CommandBounds.refusal`` words the problem from ``row`` and ``col``.
- ``Copy``, ``FollowMeasured``, ``Blend``: the joint-state broadcaster's copy and the commands of the three
  built-in modes (DAMPING, ZERO_TORQUE, STANDBY), which are also the fallback chain.

In NumPy the output check alone was a dozen calls on 14-element arrays, about 100 us a tick at 50 Hz, when the
interpreter's and NumPy's code paths have left the caches between ticks; a bound kernel call is a few tens of
nanoseconds warm. The policy controllers stay Python, around onnxruntime.

Every array a kernel indexes is checked against the shape its loops need, once per call (or when it is bound), so a
caller's mistake is a ValueError naming the array, never a read or write past a buffer."""

from libc.math cimport isfinite, isnan
from libc.string cimport memcpy

import numpy as np

# What a check found; CommandBounds.refusal has the words for each.
OK = 0
NON_FINITE = 1  # at (row, col), the first in row-major order
NEGATIVE_GAIN = 2  # stiffness (row 3) or damping (row 4): the most negative of that row, first if tied
BEYOND = 3  # |velocity|, |effort|, stiffness, damping (rows 1 to 4, in that order): the first beyond its maximum
BELOW = 4  # the first joint whose target is further than the margin below its lower limit
ABOVE = 5  # likewise above the upper limit
SHAPE = 6  # Inbox.take only: row ``row`` is not one number per joint


cdef class CommandCheck:
    """The joints' bounds: position limits with a margin, and a maximum per joint for |velocity|, |effort|,
    stiffness and damping (``maximum``, 4 x n, rows 1 to 4 of a command). ``row`` and ``col`` say where the last
    check found its problem. While ``release`` is set, a joint may have no command: a NaN position with the other
    four rows exactly zero (its drive holds on its own gains, a Sito is limp)."""

    cdef const double[::1] lower, upper
    cdef const double[:, ::1] maximum
    cdef double margin
    cdef public bint release
    cdef readonly Py_ssize_t n, row, col

    def __init__(self, const double[::1] lower not None, const double[::1] upper not None,
                 const double[:, ::1] maximum not None, double margin, bint release=False):
        cdef Py_ssize_t n = lower.shape[0]
        if upper.shape[0] != n or maximum.shape[0] != 4 or maximum.shape[1] != n:
            raise ValueError(f"the limits must have {n} joints and the maxima 4 rows of {n}")
        self.lower, self.upper, self.maximum, self.margin = lower, upper, maximum, margin
        self.release = release
        self.n = n
        self.row = self.col = -1

    def check(self, double[:, ::1] data not None):
        """Check ``data`` (5 x n), clipping a target within the margin of a limit onto it in place; OK or what
        was found, with ``row`` and ``col`` saying where."""
        if data.shape[0] != 5 or data.shape[1] != self.n:
            raise ValueError(f"command is {data.shape[0]}x{data.shape[1]}, needs 5x{self.n}")
        return self._check(data)

    cdef int _check(self, double[:, ::1] data):
        cdef Py_ssize_t n = self.n, r, j, worst
        cdef double value
        if n == 0:
            return OK
        for r in range(5):
            for j in range(n):
                if not isfinite(data[r, j]) and not (self.release and _no_command(data, j)):
                    return self._found(NON_FINITE, r, j)  # (no command passes: NaN compares false below)
        for r in (3, 4):
            worst = 0
            for j in range(1, n):
                if data[r, j] < data[r, worst]:
                    worst = j
            if data[r, worst] < 0.0:
                return self._found(NEGATIVE_GAIN, r, worst)
        for r in range(1, 5):
            for j in range(n):
                value = data[r, j]
                if (value if value >= 0.0 else -value) > self.maximum[r - 1, j]:
                    return self._found(BEYOND, r, j)
        for j in range(n):
            if data[0, j] < self.lower[j] - self.margin:
                return self._found(BELOW, 0, j)
        for j in range(n):
            if data[0, j] > self.upper[j] + self.margin:
                return self._found(ABOVE, 0, j)
        for j in range(n):
            value = data[0, j]
            data[0, j] = self.lower[j] if value < self.lower[j] else self.upper[j] if value > self.upper[j] else value
        self.row = self.col = -1
        return OK

    cdef int _found(self, int kind, Py_ssize_t row, Py_ssize_t col):
        self.row, self.col = row, col
        return kind


cdef inline bint _no_command(double[:, ::1] data, Py_ssize_t j) noexcept:
    return isnan(data[0, j]) and data[1, j] == 0.0 and data[2, j] == 0.0 and data[3, j] == 0.0 and data[4, j] == 0.0


cdef class OutputCheck:
    """The manager's per-tick handling of its proposal and command arrays (5 x n, C order): the proposal starts
    as the last command, is checked against ``bounds`` and is committed into the command."""

    cdef double[:, ::1] proposal, command
    cdef CommandCheck bounds

    def __init__(self, double[:, ::1] proposal not None, double[:, ::1] command not None,
                 CommandCheck bounds not None):
        cdef Py_ssize_t n = bounds.n
        if proposal.shape[0] != 5 or proposal.shape[1] != n or command.shape[0] != 5 or command.shape[1] != n:
            raise ValueError(f"proposal and command must both be 5 x {n}")
        self.proposal, self.command, self.bounds = proposal, command, bounds

    def propose(self):
        """The proposal starts as the last command (a controller that skips a row leaves it as it was)."""
        memcpy(&self.proposal[0, 0], &self.command[0, 0], 5 * self.bounds.n * sizeof(double))

    def commit(self):
        memcpy(&self.command[0, 0], &self.proposal[0, 0], 5 * self.bounds.n * sizeof(double))

    def check(self):
        """The bounds' check on the proposal (``CommandCheck.check``)."""
        return self.bounds._check(self.proposal)


cdef class Inbox:
    """REMOTE's door, ``take(position, velocity, effort, stiffness, damping)``: the five rows of a message, of
    any kind (lists, arrays of any dtype), checked against ``bounds`` and copied into the bound inbox (5 x n)
    when they pass; the inbox is untouched otherwise. Returns OK or what was found (SHAPE: a row that is not n
    numbers). A command arrives every tick, from the publisher's thread (DDS's on the robot): as NumPy calls
    the same checks were about 15 us a message."""

    cdef double[:, ::1] inbox, staged
    cdef CommandCheck bounds

    def __init__(self, double[:, ::1] inbox not None, CommandCheck bounds not None):
        if inbox.shape[0] != 5 or inbox.shape[1] != bounds.n:
            raise ValueError(f"the inbox must be 5 x {bounds.n}")
        self.inbox, self.bounds = inbox, bounds
        self.staged = np.zeros((5, bounds.n))

    def take(self, position, velocity, effort, stiffness, damping):
        cdef const double[::1] values
        cdef Py_ssize_t r, n = self.bounds.n
        cdef int found
        for r, row in enumerate((position, velocity, effort, stiffness, damping)):
            try:
                values = _row(row)
            except (TypeError, ValueError, BufferError):
                return self.bounds._found(SHAPE, r, -1)
            if values.shape[0] != n:
                return self.bounds._found(SHAPE, r, -1)
            if n:
                memcpy(&self.staged[r, 0], &values[0], n * sizeof(double))
        found = self.bounds._check(self.staged)
        if found == OK and n:
            memcpy(&self.inbox[0, 0], &self.staged[0, 0], 5 * n * sizeof(double))
        return found


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
    where that is finite (elsewhere it keeps the last target), within the joint limits ``[lower, upper]`` (a
    limp joint's target exerts no torque, and a measurement beyond a limit is no target to send), and the other
    four rows are zero. Bound like ``Copy``."""

    cdef object _position, _command
    cdef const double[::1] position, lower, upper
    cdef double[:, ::1] command

    def __init__(self, const double[::1] lower not None, const double[::1] upper not None):
        if lower.shape[0] != upper.shape[0]:
            raise ValueError("lower and upper limits differ in length")
        self.lower, self.upper = lower, upper

    def run(self, position, command):
        if position is not self._position or command is not self._command:
            self._bind(position, command)
        cdef Py_ssize_t j, n = self.command.shape[1]
        cdef double[:, ::1] out = self.command
        cdef double value
        for j in range(n):
            value = self.position[j]
            if isfinite(value):
                out[0, j] = self.lower[j] if value < self.lower[j] else self.upper[j] if value > self.upper[j] \
                    else value
            out[1, j] = out[2, j] = out[3, j] = out[4, j] = 0.0

    cdef _bind(self, position, command):
        cdef const double[::1] p = position
        cdef double[:, ::1] c = command
        if c.shape[0] != 5 or p.shape[0] != c.shape[1] or p.shape[0] != self.lower.shape[0]:
            raise ValueError(f"position has {p.shape[0]} entries and command is {c.shape[0]}x{c.shape[1]}, need "
                             f"{self.lower.shape[0]} and 5x{self.lower.shape[0]}")
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
            raise ValueError(f"start has {s.shape[0]} entries, delta {d.shape[0]}, command is {c.shape[0]}x"
                             f"{c.shape[1]}: need 5x{s.shape[0]} and as many of each")
        self.start, self.delta, self.command = s, d, c
        self._start, self._delta, self._command = start, delta, command


cdef const double[::1] _row(values):
    """``values`` as a C-contiguous float64 vector, without a copy when it already is one."""
    cdef const double[::1] row
    if isinstance(values, np.ndarray) and values.dtype == np.float64 and values.flags.c_contiguous:
        row = values
    else:
        row = np.ascontiguousarray(values, dtype=np.float64)
    return row


cdef extern from "<dlfcn.h>" nogil:
    void* dlopen(const char* filename, int flags)
    void* dlsym(void* handle, const char* symbol)
    char* dlerror()
    int RTLD_NOW


ctypedef void (*_kinematics_t)(const void* m, void* d) noexcept nogil
ctypedef double (*_distance_t)(const void* m, void* d, int geom1, int geom2, double distmax, double* fromto) noexcept nogil


cdef class BodyKernel:
    """The body check's per-tick work on a private MuJoCo model and data (control/body.py has the rules in words):
    ``pose`` puts a command's pose into the data and runs MuJoCo's kinematics, ``within`` finds every checked pair
    of geoms closer than the margin, with MuJoCo's own distance (``mj_geomDistance``). MuJoCo's C functions are
    called through the library the ``mujoco`` package loaded (``library``), one call each, no Python between them.

    ``qadr``: each joint's qpos address; ``pairs`` (P x 2): the geoms checked against each other; ``chains`` (P):
    the joints that move each pair (bit j for joint j); ``live`` (P): the pairs checked now, those no unknown joint
    moves. A pose comes from a command (5 x n) and the measured positions (n): the target where the
    joint has one (a finite position with stiffness above zero), else the measured position; moved into the
    model's frame by ``scale * q + shift`` per joint (the identity on a calibrated robot); a joint that is not
    ``known`` or has no finite value is unknown (``unknown``, bit j for joint j; its qpos is left at 0).
    ``within`` leaves the pairs it found in ``found`` and their distances in ``found_distance`` (``count`` of them).
    ``lower`` and ``upper``: the joints' stops in the model's frame, where a pose is clipped to."""

    cdef void* m
    cdef void* d
    cdef object _model, _data
    cdef _kinematics_t kinematics
    cdef _distance_t distance
    cdef double[::1] qpos
    cdef const double[:, ::1] xpos
    cdef const double[::1] rbound, lower, upper
    cdef const Py_ssize_t[::1] qadr
    cdef const int[:, ::1] pairs
    cdef const unsigned long long[::1] chains
    cdef unsigned char[::1] live
    cdef readonly unsigned long long unknown
    cdef const double[::1] scale, shift
    cdef const unsigned char[::1] known
    cdef readonly double margin
    cdef int[::1] found_
    cdef double[::1] found_distance_
    cdef readonly Py_ssize_t count

    def __init__(self, bytes library not None, model, data, const Py_ssize_t[::1] qadr not None,
                 const double[::1] lower not None, const double[::1] upper not None,
                 const int[:, ::1] pairs not None, const unsigned long long[::1] chains not None,
                 unsigned char[::1] live not None, double margin):
        cdef void* handle = dlopen(library, RTLD_NOW)
        if handle == NULL:
            raise OSError(f"cannot open MuJoCo's library {library.decode()}: {dlerror().decode()}")
        self.kinematics = <_kinematics_t>dlsym(handle, b"mj_kinematics")
        self.distance = <_distance_t>dlsym(handle, b"mj_geomDistance")
        if self.kinematics == NULL or self.distance == NULL:
            raise OSError(f"MuJoCo's library {library.decode()} has no mj_kinematics or mj_geomDistance")
        if pairs.shape[1] != 2 or live.shape[0] != pairs.shape[0] or chains.shape[0] != pairs.shape[0]:
            raise ValueError("pairs must be P x 2 geoms, with one chain and one live flag per pair")
        n = qadr.shape[0]
        if lower.shape[0] != n or upper.shape[0] != n:
            raise ValueError(f"the limits must have {n} joints")
        if n > 64:
            raise ValueError("at most 64 joints (the unknown joints are one bit each)")
        self._model, self._data = model, data
        self.m = <void*><size_t>model._address
        self.d = <void*><size_t>data._address
        self.qpos, self.xpos, self.rbound = data.qpos, data.geom_xpos, model.geom_rbound
        for j in range(n):
            if not 0 <= qadr[j] < self.qpos.shape[0]:
                raise ValueError(f"qadr[{j}] is {qadr[j]}, outside the model's {self.qpos.shape[0]} qpos")
        if self.xpos.shape[1] != 3 or self.rbound.shape[0] != self.xpos.shape[0]:
            raise ValueError("the model's geom_xpos and geom_rbound are not one 3-vector and one radius per geom")
        for p in range(pairs.shape[0]):
            for side in range(2):
                if not 0 <= pairs[p, side] < self.xpos.shape[0]:
                    raise ValueError(f"pairs[{p}, {side}] is {pairs[p, side]}, outside the model's "
                                     f"{self.xpos.shape[0]} geoms")
        self.qadr, self.lower, self.upper, self.pairs, self.live, self.margin = qadr, lower, upper, pairs, live, margin
        self.chains, self.unknown = chains, 0
        self.found_ = np.zeros(pairs.shape[0], dtype=np.intc)
        self.found_distance_ = np.zeros(pairs.shape[0])
        self.count = 0
        self.frame(np.ones(n), np.zeros(n), np.ones(n, dtype=np.uint8))

    def frame(self, const double[::1] scale not None, const double[::1] shift not None,
              const unsigned char[::1] known not None):
        """Bind the frame the poses are moved into the model's by (the arrays are read at every ``pose``)."""
        cdef Py_ssize_t n = self.qadr.shape[0]
        if scale.shape[0] != n or shift.shape[0] != n or known.shape[0] != n:
            raise ValueError(f"scale, shift and known have {scale.shape[0]}, {shift.shape[0]} and {known.shape[0]} "
                             f"entries, need {n} each")
        self.scale, self.shift, self.known = scale, shift, known

    def check(self, const double[:, ::1] command not None, const double[::1] measured not None,
              const double[::1] velocity not None, double horizon):
        """``pose`` and ``within`` in one call: how many live pairs the command's pose brings closer than the
        margin (the gate's every tick)."""
        self._pose(command, measured, velocity, horizon, True)
        return self._within()

    def pose(self, const double[:, ::1] command not None, const double[::1] measured not None,
             const double[::1] velocity not None, double horizon, bint targets=True):
        """The pose of ``command`` (its targets where ``targets``, else the measured positions only) into the model,
        and its kinematics. A target is taken ``horizon`` seconds further along the joint's measured ``velocity``:
        where the joint, moving, comes to rest on it. The bodies an unknown joint carries leave ``live``."""
        self._pose(command, measured, velocity, horizon, targets)

    cdef _pose(self, const double[:, ::1] command, const double[::1] measured, const double[::1] velocity,
               double horizon, bint targets):
        cdef Py_ssize_t j, p, n = self.qadr.shape[0]
        cdef double q
        cdef unsigned long long unknown = 0
        if command.shape[0] != 5 or command.shape[1] != n or measured.shape[0] != n or velocity.shape[0] != n:
            raise ValueError(f"command is {command.shape[0]}x{command.shape[1]}, measured and velocity have "
                             f"{measured.shape[0]} and {velocity.shape[0]} entries: need 5x{n}, {n} and {n}")
        for j in range(n):
            if targets and command[3, j] > 0.0 and isfinite(command[0, j]):
                q = command[0, j] + (horizon * velocity[j] if isfinite(velocity[j]) else 0.0)
            else:
                q = measured[j]
            if isfinite(q) and self.known[j]:
                q = self.scale[j] * q + self.shift[j]
                # a joint goes no further than its stops, whatever it is asked (a calibration presses beyond them)
                self.qpos[self.qadr[j]] = self.lower[j] if q < self.lower[j] else self.upper[j] if q > self.upper[j] \
                    else q
            else:
                self.qpos[self.qadr[j]] = 0.0
                unknown |= (<unsigned long long>1) << j
        if unknown != self.unknown:
            self.unknown = unknown
            for p in range(self.pairs.shape[0]):
                self.live[p] = (self.chains[p] & unknown) == 0
        self.kinematics(self.m, self.d)

    def within(self):
        """Every live pair closer than the margin at the pose last put: how many (``found``, ``found_distance``)."""
        return self._within()

    cdef Py_ssize_t _within(self):
        cdef Py_ssize_t p, count = 0
        cdef int a, b
        cdef double dx, dy, dz, reach, exact
        for p in range(self.pairs.shape[0]):
            if not self.live[p]:
                continue
            a, b = self.pairs[p, 0], self.pairs[p, 1]
            dx = self.xpos[a, 0] - self.xpos[b, 0]
            dy = self.xpos[a, 1] - self.xpos[b, 1]
            dz = self.xpos[a, 2] - self.xpos[b, 2]
            reach = self.rbound[a] + self.rbound[b] + self.margin
            if dx * dx + dy * dy + dz * dz >= reach * reach:
                continue  # their bounding spheres are further apart than the margin
            exact = self.distance(self.m, self.d, a, b, self.margin, NULL)
            if exact < self.margin:
                self.found_[count] = <int>p
                self.found_distance_[count] = exact
                count += 1
        self.count = count
        return count

    def distance_of(self, Py_ssize_t pair, double most):
        """MuJoCo's distance of ``pair`` at the pose last put, up to ``most``."""
        if not 0 <= pair < self.pairs.shape[0]:
            raise IndexError(f"no pair {pair}")
        return self.distance(self.m, self.d, self.pairs[pair, 0], self.pairs[pair, 1], most, NULL)

    @property
    def found(self):
        return np.asarray(self.found_)[:self.count]

    @property
    def found_distance(self):
        return np.asarray(self.found_distance_)[:self.count]
