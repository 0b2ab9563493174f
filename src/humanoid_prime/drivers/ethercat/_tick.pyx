# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The eRob component's per-tick work, compiled: one call reads the ring into joint state, one call turns the
MIT command into the process image. At 50 Hz the tick's cost was Python's and NumPy's per-call overhead on
ten-element arrays (dozens of calls, each paying for a cold interpreter path), not the arithmetic.

Every array is the component's own, bound once and checked then; the kernel holds no state of its own. The arrays
a call is passed (the robot's state and command, the reset flags) are checked at each call against the shape the
loops will index, so a caller's mistake is a ValueError, never a write past its buffer."""

from libc.math cimport floor, isfinite


cdef packed struct RxPdo:  # master -> drive, objects.RXPDO
    unsigned short controlword
    int target_position
    int velocity_offset
    short torque_offset
    signed char mode_of_operation
    unsigned char pad


cdef packed struct TxPdo:  # drive -> master, objects.TXPDO
    unsigned short statusword
    int position_actual
    int velocity_actual
    short torque_actual
    unsigned short error_code
    signed char mode_display
    unsigned char pad


def layouts():
    """{"rx"|"tx": ((field, byte offset), ...), plus the size}: what the structs above read and write, for the
    test that holds them to objects.RXPDO/TXPDO (a buffer check compares types, not names)."""
    cdef RxPdo rx
    cdef TxPdo tx
    cdef char* r = <char*>&rx
    cdef char* t = <char*>&tx
    return {
        "rx": ((("controlword", <char*>&rx.controlword - r), ("target_position", <char*>&rx.target_position - r),
                ("velocity_offset", <char*>&rx.velocity_offset - r), ("torque_offset", <char*>&rx.torque_offset - r),
                ("mode_of_operation", <char*>&rx.mode_of_operation - r), ("pad", <char*>&rx.pad - r)),
               sizeof(RxPdo)),
        "tx": ((("statusword", <char*>&tx.statusword - t), ("position_actual", <char*>&tx.position_actual - t),
                ("velocity_actual", <char*>&tx.velocity_actual - t), ("torque_actual", <char*>&tx.torque_actual - t),
                ("error_code", <char*>&tx.error_code - t), ("mode_display", <char*>&tx.mode_display - t),
                ("pad", <char*>&tx.pad - t)),
               sizeof(TxPdo)),
    }


cdef inline double _round_clamp(double value, double low, double high) noexcept nogil:
    """Round half up and clamp to the PDO type (as Channel.command_raw does)."""
    value = floor(value + 0.5)
    if value < low:
        return low
    if value > high:
        return high
    return value


cdef inline int _fits(str name, Py_ssize_t rows_have, Py_ssize_t columns_have, Py_ssize_t rows,
                      Py_ssize_t columns) except -1:
    """Raise unless an array of ``rows_have`` x ``columns_have`` has the ``rows`` x ``columns`` a loop indexes."""
    if rows_have < rows or columns_have < columns:
        raise ValueError(f"{name} is {rows_have}x{columns_have}, needs at least {rows}x{columns}")
    return 0


cdef class EcTick:
    """Bound to one EthercatSystem's arrays (joint order ``k``; ``ring[k]`` is the slave, ``index[k]`` the joint
    in the robot's arrays). Booleans are passed as uint8 views of the component's bool arrays."""

    cdef TxPdo[::1] inputs, rec
    cdef RxPdo[::1] outputs
    cdef const Py_ssize_t[::1] ring, index
    cdef double[:, ::1] raw, state_factor, state_offset, command_factor, command_offset
    cdef double[::1] held
    cdef unsigned char[::1] enabled, fault, state
    cdef const unsigned char[::1] chart
    cdef unsigned char state_fault, state_resetting, state_held
    cdef const unsigned short[::1] cw_table
    cdef unsigned short[::1] cw_prev, grace
    cdef public unsigned short grace_ticks  # frames in which a drive leaving its fault left it by our reset
    cdef unsigned short enabled_mask, enabled_value, fault_mask, fault_value, fault_reset, disable_voltage
    cdef signed char mode
    cdef double target_low, target_high, velocity_low, velocity_high, torque_low, torque_high
    cdef Py_ssize_t n, columns  # joints; columns the robot's arrays need (the highest joint in ``index``, plus 1)

    def __init__(self, TxPdo[::1] inputs not None, RxPdo[::1] outputs not None, TxPdo[::1] rec not None,
                 const Py_ssize_t[::1] ring not None, const Py_ssize_t[::1] index not None,
                 double[:, ::1] raw not None, double[:, ::1] state_factor not None,
                 double[:, ::1] state_offset not None, double[:, ::1] command_factor not None,
                 double[:, ::1] command_offset not None, double[::1] held not None,
                 unsigned char[::1] enabled not None, unsigned char[::1] fault not None,
                 unsigned char[::1] state not None, const unsigned char[::1] chart not None, tuple states,
                 const unsigned short[::1] cw_table not None,
                 unsigned short[::1] cw_prev not None, tuple enabled_pattern, tuple fault_pattern,
                 unsigned short fault_reset, unsigned short disable_voltage, signed char mode,
                 tuple target_limits, tuple velocity_limits, tuple torque_limits,
                 unsigned short[::1] grace not None):
        cdef Py_ssize_t n = ring.shape[0], k, needed = 0
        if cw_table.shape[0] != 0x80:
            raise ValueError(f"controlword table has {cw_table.shape[0]} entries, expected 128")
        for k in range(n):
            if not 0 <= ring[k] < inputs.shape[0] or ring[k] >= outputs.shape[0]:
                raise ValueError(f"ring position {ring[k]} outside the process image of {inputs.shape[0]} slaves")
        for k in range(index.shape[0]):
            if index[k] < 0:
                raise ValueError(f"index[{k}] is {index[k]}: a joint is a column of the robot's arrays, 0 or more")
            needed = max(needed, index[k] + 1)
        if chart.shape[0] % 3 != 0:
            raise ValueError(f"drive chart has {chart.shape[0]} entries, not 3 per state")
        for k in range(chart.shape[0]):
            if chart[k] >= chart.shape[0] // 3:
                raise ValueError(f"drive chart entry {k} goes to state {chart[k]} of {chart.shape[0] // 3}")
        for k in range(3):
            if not 0 <= states[k] < chart.shape[0] // 3:
                raise ValueError(f"state {states[k]} (fault, resetting, held) not in the drive chart's "
                                 f"{chart.shape[0] // 3}")
        for name, length in (("index", index.shape[0]), ("rec", rec.shape[0]), ("held", held.shape[0]),
                             ("enabled", enabled.shape[0]), ("fault", fault.shape[0]), ("state", state.shape[0]),
                             ("cw_prev", cw_prev.shape[0]), ("grace", grace.shape[0])):
            if length != n:
                raise ValueError(f"{name} has {length} entries for {n} joints")
        for name, rows, columns in (("raw", raw.shape[0], raw.shape[1]),
                                    ("state_factor", state_factor.shape[0], state_factor.shape[1]),
                                    ("state_offset", state_offset.shape[0], state_offset.shape[1]),
                                    ("command_factor", command_factor.shape[0], command_factor.shape[1]),
                                    ("command_offset", command_offset.shape[0], command_offset.shape[1])):
            if rows != 3 or columns != n:
                raise ValueError(f"{name} is {rows}x{columns}, expected 3x{n}")
        self.inputs, self.outputs, self.rec, self.ring, self.index = inputs, outputs, rec, ring, index
        self.raw, self.held = raw, held
        self.state_factor, self.state_offset = state_factor, state_offset
        self.command_factor, self.command_offset = command_factor, command_offset
        self.enabled, self.fault, self.state, self.chart = enabled, fault, state, chart
        self.state_fault, self.state_resetting, self.state_held = states  # drive_state: FAULT, RESETTING, HELD
        self.grace, self.grace_ticks = grace, 0
        self.cw_table, self.cw_prev = cw_table, cw_prev
        self.enabled_mask, self.enabled_value = enabled_pattern
        self.fault_mask, self.fault_value = fault_pattern
        self.fault_reset, self.disable_voltage, self.mode = fault_reset, disable_voltage, mode
        self.target_low, self.target_high = target_limits
        self.velocity_low, self.velocity_high = velocity_limits
        self.torque_low, self.torque_high = torque_limits
        self.n, self.columns = n, needed

    cdef int _fits_reset(self, const unsigned char[::1] reset) except -1:
        if reset is not None and reset.shape[0] < self.n:
            raise ValueError(f"reset has {reset.shape[0]} entries, needs at least {self.n} (one per drive)")
        return 0

    cpdef int gather(self):
        """The inputs of this component's slaves into joint order (``rec``, ``raw``), and which drives are
        enabled or faulted; returns how many are faulted."""
        cdef Py_ssize_t k
        cdef int faulted = 0
        cdef unsigned short sw
        for k in range(self.n):
            self.rec[k] = self.inputs[self.ring[k]]
            sw = self.rec[k].statusword
            self.raw[0, k] = self.rec[k].position_actual
            self.raw[1, k] = self.rec[k].velocity_actual
            self.raw[2, k] = self.rec[k].torque_actual
            self.enabled[k] = (sw & self.enabled_mask) == self.enabled_value
            self.fault[k] = (sw & self.fault_mask) == self.fault_value
            faulted += self.fault[k]
        return faulted

    def read(self, double[:, ::1] state not None):
        """Gather, move each drive's state (drive_state.FRAME_CHART, one row per state, one column per what the
        frame says: enabled, fault, other), and write position, velocity and effort into ``state``. A drive whose
        fault reset is under way (RESETTING) and still in fault after ``grace_ticks`` frames is latched again.
        Returns (drives in fault, whether a drive entered or left a held state)."""
        cdef Py_ssize_t k, row
        cdef int faulted
        cdef bint held_changed = False
        cdef unsigned char before, seen, now
        _fits("state", state.shape[0], state.shape[1], 3, self.columns)
        faulted = self.gather()
        for k in range(self.n):
            seen = 0 if self.enabled[k] else (1 if self.fault[k] else 2)
            before = self.state[k]
            now = self.chart[before * 3 + seen]
            if now == self.state_resetting and seen == 1:
                if self.grace[k]:
                    self.grace[k] -= 1
                if not self.grace[k]:
                    now = self.state_fault
            self.state[k] = now
            held_changed |= (before >= self.state_held) != (now >= self.state_held)
            for row in range(3):
                state[row, self.index[k]] = self.raw[row, k] * self.state_factor[row, k] + self.state_offset[row, k]
        return faulted, held_changed

    def controlwords(self, const unsigned char[::1] reset=None):
        """Per drive, the controlword one step toward enabled. Drives in ``reset`` that are in fault get a fault
        reset; a fault reset is a rising edge, so it alternates with disable voltage, and a faulted drive it goes to
        is RESETTING for ``grace_ticks`` frames. A held drive gets disable voltage."""
        cdef Py_ssize_t k
        cdef unsigned short cw
        self._fits_reset(reset)
        for k in range(self.n):
            cw = self.cw_table[self.rec[k].statusword & 0x7F]
            if self.fault[k] and reset is not None and reset[k]:
                cw = self.fault_reset
            if self.state[k] >= self.state_held:
                cw = self.disable_voltage
            if cw == self.fault_reset and self.cw_prev[k] == self.fault_reset:
                cw = self.disable_voltage
            if cw == self.fault_reset:  # leaving the fault within grace_ticks frames is this reset's doing
                self.grace[k] = self.grace_ticks
                if self.state[k] < self.state_held:
                    self.state[k] = self.state_resetting
            self.cw_prev[k] = cw
            self.outputs[self.ring[k]].controlword = cw

    def write(self, const double[:, ::1] command not None, const unsigned char[::1] reset=None):
        """The MIT command (rows position, velocity, effort, stiffness, damping; robot order) into the
        process image, then the controlwords.

        Position is the CSP target; NaN holds the last target sent; zero stiffness, or a drive that is not
        enabled, follows the actual position. The velocity and torque offsets (the damping term's and the
        effort's feed-forward) are zero where not finite or where the drive is not enabled."""
        cdef Py_ssize_t k, j, slave
        cdef double target, velocity, torque
        _fits("command", command.shape[0], command.shape[1], 5, self.columns)
        self._fits_reset(reset)
        for k in range(self.n):
            j, slave = self.index[k], self.ring[k]
            target = command[0, j] * self.command_factor[0, k] + self.command_offset[0, k]
            if not isfinite(target):
                target = self.held[k]
            elif command[3, j] == 0.0:
                target = self.raw[0, k]
            if not self.enabled[k]:
                target = self.raw[0, k]
            target = _round_clamp(target, self.target_low, self.target_high)
            self.held[k] = target
            self.outputs[slave].target_position = <int>target
            velocity = command[1, j] * self.command_factor[1, k] + self.command_offset[1, k]
            torque = command[2, j] * self.command_factor[2, k] + self.command_offset[2, k]
            if not (isfinite(velocity) and self.enabled[k]):
                velocity = 0.0
            if not (isfinite(torque) and self.enabled[k]):
                torque = 0.0
            self.outputs[slave].velocity_offset = <int>_round_clamp(velocity, self.velocity_low, self.velocity_high)
            self.outputs[slave].torque_offset = <short>_round_clamp(torque, self.torque_low, self.torque_high)
        for slave in range(self.outputs.shape[0]):
            self.outputs[slave].mode_of_operation = self.mode
        self.controlwords(reset)
