"""A line of emulated eRob slaves: passes each frame through the slaves in ring order, keeps the
working counters, and advances the drives and their plant in real time.

Addressing as the ESCs do it: auto-increment commands (APxx, ARMW) address the slave that sees ADP 0,
each slave adding one to ADP on the way; configured-address commands (FPxx, FRMW) the slave whose
0x0010 equals ADP; broadcast commands every slave (each also adding one to ADP); logical commands every
slave whose FMMUs overlap the logical range. Working counter per addressed slave: read +1, write +1,
read-write +1 read and +2 write (LRW likewise); ARMW/FRMW: the addressed slave reads (+1), every other
slave writes (+1). Broadcast reads OR the slaves' data. A frame that does not parse is dropped.

A lost slave (power off) cuts the line there: it and the slaves behind it no longer see frames, and the
slave before it closes its port 1.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable

import numpy as np

from humanoid_prime.drivers.ethercat.wire import DATAGRAM_HEADER_SIZE, REG_DC_SYSTEM_TIME, Command
from humanoid_prime.virtual.plant import Plant, make_ring_plant
from humanoid_prime.virtual.ring.firmware import ErobFirmware
from humanoid_prime.virtual.ring.frames import FrameError, iter_datagrams
from humanoid_prime.virtual.ring.latency import MailboxLatency
from humanoid_prime.virtual.ring.options import RingOptions

_U16 = struct.Struct("<H")
_ADDRESS = struct.Struct("<HH")
_MAX_CATCH_UP_NS = 50_000_000  # further behind than this, the physics skips ahead instead of integrating

_AUTO = (Command.APRD, Command.APWR, Command.APRW, Command.ARMW)
_CONFIGURED = (Command.FPRD, Command.FPWR, Command.FPRW, Command.FRMW)
_BROADCAST = (Command.BRD, Command.BWR, Command.BRW)
_LOGICAL = (Command.LRD, Command.LWR, Command.LRW)
_READS = (Command.APRD, Command.FPRD, Command.BRD)
_WRITES = (Command.APWR, Command.FPWR, Command.BWR)


class Ring:
    """The emulated slaves in ring order, their plant and the SDO write log."""

    def __init__(self, options: RingOptions, plant: Plant | None = None,
                 clock: Callable[[], int] = time.monotonic_ns) -> None:
        options.check()
        self.options = options
        self.clock = clock
        now = clock()
        self.sdo_log: list[tuple[float, int, int, int, int, bool]] = []
        self.latency = MailboxLatency(options)
        self.slaves = [ErobFirmware(i, options, clock_origin_ns=now - 1_000_003 * (i + 1), log=self._log,
                                    latency=self.latency)
                       for i in range(options.slaves)]
        self.plant = (plant if plant is not None
                      else make_ring_plant(options.plant, options.slaves, options.physics_dt_s))
        if self.plant.n != options.slaves:
            raise ValueError(f"plant has {self.plant.n} joints for {options.slaves} slaves")
        self.powered = [True] * options.slaves
        self.reachable = list(self.slaves)
        self.frames = 0
        self.dropped_malformed = 0
        self._sim_ns = now
        self._dt_ns = round(options.physics_dt_s * 1e9)
        self._torque = np.zeros(options.slaves)
        self._braked = np.ones(options.slaves, dtype=bool)
        self._hit = [False] * options.slaves
        self._pending_frame: tuple[int, bool, bool] | None = None  # (time, DC time distributed, process data)
        self._frame_ns = now  # when the latest frame passed
        # the server's: answer the frames that arrived while a step runs, between its parts (an ESC answers in
        # microseconds; a whole step of the robot's Python is hundreds, and a master's state read waits it out)
        self.serve_waiting: Callable[[], None] | None = None
        self._update_topology()
        self.advance(now)

    def _log(self, t: float, position: int, index: int, sub: int, value: int, applied: bool) -> None:
        self.sdo_log.append((t, position, index, sub, value, applied))

    # ---- topology ----------------------------------------------------------------------------------------
    def _update_topology(self) -> None:
        reachable = []
        for slave, powered in zip(self.slaves, self.powered, strict=True):
            if not powered:
                break
            reachable.append(slave)
        self.reachable = reachable
        hop = self.options.hop_delay_ns
        last = len(reachable) - 1
        for i, slave in enumerate(reachable):
            slave.esc.set_links(port1_open=i < last)
            slave.esc.clock.port0_delay_ns = i * hop
            slave.esc.clock.port1_delay_ns = (2 * last - i) * hop if i < last else None

    def lose(self, position: int) -> None:
        """Power off the slave at ``position``: the line ends before it."""
        self.finish_frame()
        self.powered[position] = False
        self._update_topology()

    def restore(self, position: int) -> None:
        """Power the slave at ``position`` on again; it starts in INIT with fresh registers."""
        self.finish_frame()
        if not self.powered[position]:
            self.slaves[position].power_cycle(self.clock())
            self.powered[position] = True
            self._update_topology()

    # ---- frames ------------------------------------------------------------------------------------------
    def process(self, frame: bytearray, now_ns: int) -> bool:
        """Pass ``frame`` (one Ethernet frame, changed in place) through the reachable slaves; False if it
        was dropped as malformed."""
        try:
            datagrams = list(iter_datagrams(frame))
        except FrameError:
            self.dropped_malformed += 1
            return False
        self.finish_frame()
        self.frames += 1
        self._frame_ns = now_ns
        slaves = self.reachable
        hit = self._hit
        for slave in slaves:
            slave.esc.frame_time_ns = now_ns
            slave.deliver_replies(now_ns)
        time_distributed = cyclic = False
        for command, offset, length in datagrams:
            data = offset + DATAGRAM_HEADER_SIZE
            wkc_at = data + length
            adp, ado = _ADDRESS.unpack_from(frame, offset + 2)
            wkc = _U16.unpack_from(frame, wkc_at)[0]
            if command in _LOGICAL:
                address = (ado << 16) | adp
                for i, slave in enumerate(slaves):
                    increment = slave.esc.logical(command, address, frame, data, length)
                    if increment:
                        wkc += increment
                        hit[i] = cyclic = True
            elif command in _CONFIGURED:
                if command == Command.FRMW:
                    if ado == REG_DC_SYSTEM_TIME:
                        time_distributed = True
                    wkc += self._read_multiple_write(frame, data, length, ado,
                                                     [s.esc.station_address == adp for s in slaves])
                else:
                    for slave in slaves:
                        if slave.esc.station_address == adp:
                            wkc += _physical(command, slave, ado, frame, data, length)
            elif command in _AUTO:
                addressed = [(adp + i) & 0xFFFF == 0 for i in range(len(slaves))]
                _U16.pack_into(frame, offset + 2, (adp + len(slaves)) & 0xFFFF)
                if command == Command.ARMW:
                    if ado == REG_DC_SYSTEM_TIME:
                        time_distributed = True
                    wkc += self._read_multiple_write(frame, data, length, ado, addressed)
                else:
                    for slave, is_it in zip(slaves, addressed, strict=True):
                        if is_it:
                            wkc += _physical(command, slave, ado, frame, data, length)
            elif command in _BROADCAST:
                _U16.pack_into(frame, offset + 2, (adp + len(slaves)) & 0xFFFF)
                for slave in slaves:
                    wkc += _physical(command, slave, ado, frame, data, length)
            _U16.pack_into(frame, wkc_at, wkc & 0xFFFF)
        self._pending_frame = (now_ns, time_distributed, cyclic)
        return True

    def finish_frame(self) -> None:
        """The slaves' reaction to the last frame (DC lock, AL changes, new outputs to the drives); runs after
        the reply is on its way, before the next frame or time step."""
        if self._pending_frame is None:
            return
        now_ns, time_distributed, cyclic = self._pending_frame
        self._pending_frame = None
        hit = self._hit
        for i, slave in enumerate(self.reachable):
            if cyclic and slave.pending_change is not None:  # the master's cycle went on while this slave changed state
                slave.change_frames[-1] += 1
            if hit[i]:
                hit[i] = False
                slave.on_cycle(now_ns, time_distributed)
            if slave.outputs_pending:
                slave.apply_outputs()

    def _read_multiple_write(self, frame: bytearray, data: int, length: int, ado: int,
                             addressed: list[bool]) -> int:
        wkc = 0
        for slave, is_it in zip(self.reachable, addressed, strict=True):
            if is_it:
                wkc += slave.esc.read(ado, frame, data, length)
            else:
                wkc += slave.esc.write(ado, frame, data, length)
        return wkc

    # ---- time --------------------------------------------------------------------------------------------
    def advance(self, now_ns: int, max_steps: int | None = None) -> bool:
        """Integrate drives and plant up to ``now_ns`` (at most ``max_steps`` physics steps of it), run the
        slaves' timed checks and refresh their inputs; True when the physics has caught up with ``now_ns``.
        Frames that arrive meanwhile are answered between the drives' step and the plant's, after the plant's, and
        before the timed checks (``serve_waiting``)."""
        self.finish_frame()
        dt_ns = self._dt_ns
        if now_ns - self._sim_ns > _MAX_CATCH_UP_NS:
            self._sim_ns = now_ns - dt_ns
        until_ns = now_ns if max_steps is None else min(now_ns, self._sim_ns + max_steps * dt_ns)
        plant = self.plant
        slaves = self.slaves
        powered = self.powered
        torque = self._torque
        braked = self._braked
        dt = dt_ns / 1e9
        serve = self.serve_waiting
        while self._sim_ns + dt_ns <= until_ns:
            q = plant.q.tolist()
            qd = plant.qd.tolist()
            for i, slave in enumerate(slaves):
                drive = slave.drive
                if powered[i]:
                    torque[i] = drive.step(q[i], qd[i], dt)
                    braked[i] = drive.braked
                else:
                    torque[i] = 0.0
                    braked[i] = True
            if serve is not None:
                serve()
                self.finish_frame()
            plant.step(torque, braked, dt)
            self._sim_ns += dt_ns
            if serve is not None:
                serve()
                self.finish_frame()
        if serve is not None:  # frames that came while this process was not running have reached the ESCs by now:
            serve()  # they count before the timed checks (an output watchdog must not run out on a frame in the queue)
            self.finish_frame()
        q = plant.q.tolist()
        qd = plant.qd.tolist()
        checked_ns = max(now_ns, self._frame_ns)  # never before a frame these slaves have already answered
        for i, slave in enumerate(slaves):
            if not powered[i] or slave.silent:
                continue
            slave.tick(checked_ns)
            slave.drive.update_feedback(q[i], qd[i])
            slave.refresh_inputs()
        return self._sim_ns + dt_ns > now_ns


def _physical(command: int, slave: ErobFirmware, ado: int, frame: bytearray, data: int, length: int) -> int:
    esc = slave.esc
    if command in _READS:
        return int(esc.read(ado, frame, data, length, combine=command == Command.BRD))
    if command in _WRITES:
        return int(esc.write(ado, frame, data, length))
    original = bytes(frame[data:data + length])
    did_read = esc.read(ado, frame, data, length, combine=command == Command.BRW)
    did_write = esc.write(ado, original, 0, length)
    return int(did_read) + 2 * int(did_write)
