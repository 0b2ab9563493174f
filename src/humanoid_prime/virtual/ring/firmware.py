"""The application side of one emulated eRob slave: AL state machine, CoE mailbox with latency, process
data to and from the drive, output watchdog, and the DC lock and SYNC0 supervision.

AL state machine (ETG.1000.6): INIT -> PRE-OP needs the mailbox SyncManagers as the SII describes them
(else 0x0016); PRE-OP -> SAFE-OP needs SM2/SM3 matching the PDO mapping in 0x1C12/0x1C13 (else
0x001D/0x001E); SAFE-OP -> OP is described below; skipping a state is refused with 0x0011, BOOT with
0x0013. With the error flag set, only requests to a lower state are served until the master writes
the acknowledge bit. Outputs (SM2) count in the working counter only in OP, inputs (SM3) in SAFE-OP and
OP: the slave deactivates the SyncManager otherwise.

DC model. SYNC0 runs once 0x0981 = 3 and the system time has reached the start time 0x0990 (a start
time already past at activation never starts, as on a real ESC). A slave locks after ``dc_lock_cycles``
process-data frames that also carry the master's time distribution (the FRMW/ARMW on 0x0910), each no
more than ``SYNC0 cycle * (1 + sync_tolerance)`` after the previous one; a longer gap (SYNC0 faster
than the frames) restarts the count, so a SYNC0 faster than the frame rate never locks. So does a frame
whose time distribution finds the slave's system time more than ``dc_sync_window_ns`` off the reference
clock's (0x092C): SYNC0 runs on the slave's own copy of the ring's time, and a copy that far off (a slave
back from a power cycle whose offset the master did not set again, or a ring whose reference clock
started again from 0) puts SYNC0 out of step with the frames. A locked slave in SAFE-OP loses its lock on
such a frame. SAFE-OP -> OP waits, without error, until the slave has locked (a pending OP request
completes then). In OP, ``sync_fault_cycles`` consecutive gaps longer than that, or frames that far off,
fault the drive (0xA000) and drop the slave to SAFE-OP with AL code 0x001A. In OP with SYNC0 not running,
a drive enabled in CSP faults at once (0xA000): CSP needs DC. A mailbox request while SYNC0 is on but not
yet locked (the activation phase) faults the drive with 0xA000 and restarts the lock. A SYNC0 cycle below
500 us is refused at SAFE-OP -> OP (0x0035).

Watchdog: in OP, no output write for the ESC's SM watchdog time (100 ms by default) -> SAFE-OP with AL
code 0x001B. Leaving OP while the drive is enabled faults it with 0xA000.

Mailbox SyncManagers: a master that switches SM0 or SM1 off, or moves them, in PRE-OP or above drops the slave
to INIT with AL code 0x0016 (invalid mailbox configuration), as Beckhoff's slave stack does on the SM change
event; its reply mailbox is gone until the master configures it again. How long replies take is the ring's
``MailboxLatency``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from humanoid_prime.drivers.erob import objects as obj
from humanoid_prime.drivers.erob.constants import MIN_CYCLE_S, PRODUCT_CODE, VENDOR_ID
from humanoid_prime.drivers.ethercat.wire import (
    AL_CODE_BOOTSTRAP_NOT_SUPPORTED,
    AL_CODE_INVALID_MAILBOX_CONFIG,
    AL_CODE_INVALID_STATE_CHANGE,
    AL_CODE_INVALID_SYNC_CYCLE,
    AL_CODE_NO_ERROR,
    AL_CODE_NO_SYNC,
    AL_CODE_SYNC_ERROR,
    AL_CODE_UNKNOWN_STATE,
    AL_CODE_WATCHDOG,
    AL_ERROR,
    AL_STATE_MASK,
    DC_CYCLIC_SYNC0,
    SM_ENABLE,
    AlState,
)
from humanoid_prime.virtual.ring import sii
from humanoid_prime.virtual.ring.drive import ERROR_COMMUNICATION, REVISION, ErobDrive
from humanoid_prime.virtual.ring.esc import Esc
from humanoid_prime.virtual.ring.latency import MailboxLatency
from humanoid_prime.virtual.ring.mailbox import CoeServer
from humanoid_prime.virtual.ring.options import RingOptions
from humanoid_prime.virtual.ring.pdo import (
    MAX_PDO_BYTES,
    SM_INPUTS,
    SM_OUTPUTS,
    ProcessData,
    compile_process_data,
    guard_pdo_objects,
)
from humanoid_prime.virtual.ring.quirks import SLOW_SII_S, SLOW_STATE_S

MAILBOX_OUT_START = 0x1000
MAILBOX_IN_START = 0x1080
OUTPUTS_START = 0x1100
SM_MAILBOX_OUT_CONTROL, SM_MAILBOX_IN_CONTROL = 0x26, 0x22  # mailbox, ECAT writes / reads, interrupts on
SM_OUTPUTS_CONTROL, SM_INPUTS_CONTROL = 0x64, 0x20  # buffered, ECAT writes (watchdog trigger) / reads

# A write the slave logged: (monotonic s, ring position, index, subindex, raw value, applied).
SdoLogSink = Callable[[float, int, int, int, int, bool], None]


def sii_content(options: RingOptions, serial: int) -> sii.SiiContent:
    size = options.mailbox_size
    return sii.SiiContent(
        vendor_id=VENDOR_ID, product_code=PRODUCT_CODE, revision=REVISION, serial=serial,
        name="eRob CiA402 (emulated)", group="Servo drives", order="eRob70",
        sync_managers=(
            sii.SyncManagerLayout(MAILBOX_OUT_START, size, SM_MAILBOX_OUT_CONTROL, sii.SM_TYPE_MAILBOX_OUT),
            sii.SyncManagerLayout(MAILBOX_IN_START if size <= 0x80 else MAILBOX_OUT_START + size, size,
                                  SM_MAILBOX_IN_CONTROL, sii.SM_TYPE_MAILBOX_IN),
            sii.SyncManagerLayout(_outputs_start(size), _size(obj.POWER_UP_RXPDO), SM_OUTPUTS_CONTROL,
                                  sii.SM_TYPE_OUTPUTS),
            sii.SyncManagerLayout(_outputs_start(size) + MAX_PDO_BYTES, _size(obj.POWER_UP_TXPDO), SM_INPUTS_CONTROL,
                                  sii.SM_TYPE_INPUTS),
        ),
        rx_pdo_index=obj.RXPDO_MAP, rx_pdo=obj.POWER_UP_RXPDO, tx_pdo_index=obj.TXPDO_MAP, tx_pdo=obj.POWER_UP_TXPDO,
    )


def _size(entries: tuple[obj.PdoEntry, ...]) -> int:
    return sum(entry.bits for entry in entries) // 8


def _outputs_start(mailbox_size: int) -> int:
    return max(OUTPUTS_START, MAILBOX_OUT_START + 2 * mailbox_size)


class ErobFirmware:
    """Glue between one ESC and one drive model. ``tick(now)`` runs the time-driven parts."""

    def __init__(self, position: int, options: RingOptions, *, clock_origin_ns: int,
                 log: SdoLogSink | None = None, latency: MailboxLatency | None = None) -> None:
        self.position = position
        self.options = options
        self.quirks = options.quirk_profiles
        self.log = log
        self.latency = latency if latency is not None else MailboxLatency(options)
        serial = 0x00E20000 + position
        self.drive = self._new_drive(serial)
        self.esc = Esc(sii.build_image(sii_content(options, serial)), self, clock_origin_ns=clock_origin_ns,
                       eeprom_busy_s=SLOW_SII_S if "slow-sii" in self.quirks else 0.0)
        self.coe = self._new_coe()
        self.state = AlState.INIT
        self.error = False
        self.code = AL_CODE_NO_ERROR
        self.pending_op = False
        self.pending_change: tuple[int, int] | None = None  # (requested state, due ns): a state change under way
        self.change_frames: list[int] = []  # per delayed state change, process-data frames the ring carried meanwhile
        self.silent = False
        self.locked = False
        self.lock_count = 0
        self.sync_mismatch = 0
        self.last_cycle_ns: int | None = None
        self.outputs_pending = False
        self.process_data: ProcessData | None = None
        self.mailbox_faults = 0
        self.refusals: dict[int, int] = {}  # fault injection: requests for a state here are refused with that code
        self.replies_taken = 0  # replies the master read out of the read mailbox (a repeated one counts again)
        self._replies: deque[tuple[int, bytes]] = deque()
        guard_pdo_objects(self.drive.od, self._in_pre_op)
        self._enter(AlState.INIT)

    @property
    def state_change_s(self) -> float:
        """How long a request for PRE-OP or SAFE-OP from a lower state takes to be carried out."""
        slow = SLOW_STATE_S if "slow-states" in self.quirks else 0.0
        return max(self.options.state_change_s, slow)

    # ---- ESC callbacks ------------------------------------------------------------------------------
    def al_control(self, value: int) -> None:
        if self.silent:
            return
        requested = value & AL_STATE_MASK
        if value & AL_ERROR:
            self.error = False
            if "slow-states" not in self.quirks:  # that profile leaves the code set (the master ignores it now)
                self.code = AL_CODE_NO_ERROR
        elif self.error and requested >= self.state:
            return
        if self.pending_change is not None and self.pending_change[0] == requested:
            return  # asked again while it is under way
        self.pending_change = None
        if self.state_change_s and requested in (AlState.PRE_OP, AlState.SAFE_OP) and requested > self.state:
            self.pending_change = (requested, self.esc.frame_time_ns + round(self.state_change_s * 1e9))
            self.change_frames.append(0)
            return
        self._request(requested)
        self._publish()

    def mailbox_received(self, message: bytes) -> bool:
        if self.silent:
            return False
        now = self.esc.frame_time_ns
        if self.in_dc_activation:
            self.drive.fault(ERROR_COMMUNICATION)
            self.mailbox_faults += 1
            self.locked = False
            self.lock_count = 0
        self._replies.extend((now + self.latency.delay_ns(self.position), reply)  # each posted once SM1 is free
                             for reply in self.coe.handle(message))
        self._post_reply(now)
        return True

    def mailbox_read(self) -> None:
        self.replies_taken += 1
        self._post_reply(self.esc.frame_time_ns)

    def mailbox_changed(self) -> None:
        """The master wrote SM0 or SM1: above INIT, a mailbox switched off or moved drops the slave to INIT."""
        if not self.silent and self.state != AlState.INIT and not self._mailbox_config_ok():
            self._fail(AL_CODE_INVALID_MAILBOX_CONFIG, AlState.INIT)

    def outputs_written(self) -> None:
        self.outputs_pending = True

    def sync_activation_changed(self) -> None:
        if not self._sync0_on:
            self.locked = False
            self.lock_count = 0
        cycle = self.esc.clock.sync0_cycle_ns
        for index in (obj.SYNC_OUTPUT, obj.SYNC_INPUT):
            self.drive.od.set(index, 2, cycle)

    def set_silent(self, silent: bool) -> None:
        """Freeze or thaw the firmware; thawing serves a request left in the write mailbox meanwhile."""
        self.silent = silent
        if not silent:
            request = self.esc.take_mailbox_request()
            if request is not None:
                self.mailbox_received(request)

    # ---- status ---------------------------------------------------------------------------------------
    @property
    def _sync0_on(self) -> bool:
        return self.esc.clock.activation & DC_CYCLIC_SYNC0 == DC_CYCLIC_SYNC0

    @property
    def in_dc_activation(self) -> bool:
        return self._sync0_on and not self.locked and self.state in (AlState.SAFE_OP, AlState.OP)

    def _in_pre_op(self) -> bool:
        return self.state == AlState.PRE_OP

    # ---- AL state machine -------------------------------------------------------------------------------
    def _request(self, requested: int) -> None:
        current = self.state
        self.pending_op = False
        if requested == current:
            return
        if requested in self.refusals:
            self._fail(self.refusals[requested])
            return
        if requested == AlState.INIT:
            self._enter(AlState.INIT)
        elif requested == AlState.PRE_OP:
            if current == AlState.INIT and not self._mailbox_config_ok():
                self._fail(AL_CODE_INVALID_MAILBOX_CONFIG)
            else:
                self._enter(AlState.PRE_OP)
        elif requested == AlState.SAFE_OP:
            if current == AlState.INIT:
                self._fail(AL_CODE_INVALID_STATE_CHANGE)
            elif current == AlState.PRE_OP:
                compiled = compile_process_data(self.drive.od, self.esc)
                if isinstance(compiled, int):
                    self._fail(compiled)
                else:
                    self.process_data = compiled
                    self._enter(AlState.SAFE_OP)
            else:
                self._enter(AlState.SAFE_OP)
        elif requested == AlState.OP:
            self._request_op(current)
        elif requested == AlState.BOOT:
            self._fail(AL_CODE_BOOTSTRAP_NOT_SUPPORTED)
        else:
            self._fail(AL_CODE_UNKNOWN_STATE)

    def _request_op(self, current: int) -> None:
        clock = self.esc.clock
        if current != AlState.SAFE_OP:
            self._fail(AL_CODE_INVALID_STATE_CHANGE)
        elif self._sync0_on and clock.sync0_cycle_ns < MIN_CYCLE_S * 1e9:
            self._fail(AL_CODE_INVALID_SYNC_CYCLE)
        elif "slow-states" in self.quirks and not clock.sync0_running(self.esc.frame_time_ns):
            self._fail(AL_CODE_NO_SYNC)  # asked before its first SYNC0: refused, the master acknowledges and asks again
        elif self._sync0_on and not self.locked:
            self.pending_op = True
        else:
            self._enter(AlState.OP)

    def _fail(self, code: int, fallback: AlState | None = None) -> None:
        self.error = True
        self.code = code
        if fallback is not None and fallback < self.state:
            self._enter(fallback)
        self._publish()

    def _publish(self) -> None:
        self.esc.set_al_status(int(self.state), self.error, self.code)

    def _enter(self, state: AlState) -> None:
        previous = self.state
        self.state = state
        self.pending_op = False
        esc = self.esc
        if previous == AlState.OP and state != AlState.OP and self.drive.csp_enabled:
            self.drive.fault(ERROR_COMMUNICATION)
        esc.set_sm_deactivated(SM_OUTPUTS, state != AlState.OP)
        esc.set_sm_deactivated(SM_INPUTS, state not in (AlState.SAFE_OP, AlState.OP))
        if state == AlState.OP:
            esc.last_output_write_ns = esc.frame_time_ns
            self.sync_mismatch = 0
        if state <= AlState.PRE_OP:
            self.locked = False
            self.lock_count = 0
            self.outputs_pending = False
        if state == AlState.INIT:
            self.coe.reset()
            self._replies.clear()
            esc.clear_mailboxes()
        self._publish()

    def _mailbox_config_ok(self) -> bool:
        size = self.options.mailbox_size
        out_start, out_length, out_control, out_activate = self.esc.sync_manager(0)
        in_start, in_length, in_control, in_activate = self.esc.sync_manager(1)
        expected = sii_content(self.options, 0).sync_managers
        return (out_start == expected[0].start and out_length == size and out_control & 0x0F == 0x06
                and out_activate & SM_ENABLE and in_start == expected[1].start and in_length == size
                and in_control & 0x0F == 0x02 and in_activate & SM_ENABLE)

    # ---- mailbox ------------------------------------------------------------------------------------------
    def _downloaded(self, index: int, sub: int, data: bytes) -> None:
        if self.log is not None:
            applied = self.drive.last_gain_write_applied if index in (0x2381, 0x2382) else True
            self.log(self.esc.frame_time_ns / 1e9, self.position, index, sub, int.from_bytes(data, "little"), applied)

    def _post_reply(self, now_ns: int) -> None:
        if self._replies and self._replies[0][0] <= now_ns and not self.esc.reply_mailbox_full:
            self.esc.post_mailbox(self._replies.popleft()[1])

    # ---- process data and time ---------------------------------------------------------------------------
    def on_cycle(self, now_ns: int, time_distributed: bool) -> None:
        """A process-data frame reached this slave's FMMUs (``time_distributed``: it also carried the
        master's 0x0910 time distribution)."""
        if self.silent:
            return
        previous = self.last_cycle_ns
        self.last_cycle_ns = now_ns
        clock = self.esc.clock
        if self.state not in (AlState.SAFE_OP, AlState.OP) or not clock.sync0_running(now_ns):
            return
        limit = clock.sync0_cycle_ns * (1.0 + self.options.sync_tolerance)
        too_slow = previous is not None and now_ns - previous > limit
        difference = clock.difference_ns if clock.sample_ns == now_ns else None  # this frame's sample
        off_time = time_distributed and difference is not None and abs(difference) > self.options.dc_sync_window_ns
        if not self.locked:
            if too_slow or off_time:
                self.lock_count = 0
            elif time_distributed:
                self.lock_count += 1
                if self.lock_count >= self.options.dc_lock_cycles:
                    self.locked = True
                    if self.pending_op:
                        self._enter(AlState.OP)
            return
        if self.state != AlState.OP:
            if off_time:
                self.locked = False
                self.lock_count = 0
            return
        self.sync_mismatch = self.sync_mismatch + 1 if too_slow or off_time else 0
        if self.sync_mismatch >= self.options.sync_fault_cycles:
            self.sync_mismatch = 0
            self.drive.fault(ERROR_COMMUNICATION)
            self.locked = False
            self.lock_count = 0
            self._fail(AL_CODE_SYNC_ERROR, AlState.SAFE_OP)

    def apply_outputs(self) -> None:
        """Decode outputs the master completed in this frame and let the drive react."""
        self.outputs_pending = False
        if self.silent or self.process_data is None or self.state != AlState.OP:
            return
        self.process_data.rx.unpack(self.esc.mem, self.process_data.outputs_at)
        self.drive.process_outputs()

    def refresh_inputs(self) -> None:
        if self.silent or self.process_data is None:
            return
        self.process_data.tx.pack(self.esc.mem, self.process_data.inputs_at)

    def deliver_replies(self, now_ns: int) -> None:
        """Move a mailbox reply whose latency has passed into the read mailbox."""
        if self._replies and not self.silent:
            self._post_reply(now_ns)

    def tick(self, now_ns: int) -> None:
        """Time-driven checks: delayed mailbox replies, output watchdog, CSP without DC."""
        if self.silent:
            return
        if self._replies:
            self._post_reply(now_ns)
        if self.pending_change is not None and now_ns >= self.pending_change[1]:
            requested, self.pending_change = self.pending_change[0], None
            self._request(requested)
            self._publish()
        if self.state != AlState.OP:
            return
        watchdog = self.esc.output_watchdog_ns
        last = self.esc.last_output_write_ns
        if watchdog and last is not None and now_ns - last > watchdog:
            self._fail(AL_CODE_WATCHDOG, AlState.SAFE_OP)
            return
        if self.drive.csp_enabled and not self.esc.clock.sync0_running(now_ns):
            self.drive.fault(ERROR_COMMUNICATION)

    def _new_drive(self, serial: int) -> ErobDrive:
        return ErobDrive(serial, gain_bytes=self.options.gain_bytes, rated_torque_mnm=self.options.rated_torque_mnm)

    def _new_coe(self) -> CoeServer:
        # with the "counter" profile its replies' counter starts anywhere (one value per ring position)
        first = (3 * self.position + 4) % 7 if "counter" in self.quirks else 0
        return CoeServer(self.drive.od, self.options.mailbox_size, on_download=self._downloaded, quirks=self.quirks,
                         first_counter=first)

    def power_cycle(self, now_ns: int | None = None) -> None:
        """The slave lost power and came back at ``now_ns``: ESC registers, its local clock, AL state and the drive
        start afresh."""
        self.drive = self._new_drive(self.drive.serial)  # the same model as before, factory state
        self.coe = self._new_coe()
        guard_pdo_objects(self.drive.od, self._in_pre_op)
        self.esc.power_on(now_ns)
        self.pending_change = None
        self.state = AlState.INIT
        self.error = False
        self.code = AL_CODE_NO_ERROR
        self.process_data = None
        self.last_cycle_ns = None
        self._enter(AlState.INIT)
