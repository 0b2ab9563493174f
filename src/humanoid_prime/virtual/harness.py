"""Run the virtual Prime beside this process, inside a private network namespace.

``enter_private_netns()`` re-executes the current command inside a fresh network namespace (``unshare -n``
as root, ``unshare -rn`` otherwise), so nothing the emulation creates — a veth pair, a multicast route,
CAN traffic — is visible on the host, and all of it disappears with the process. Inside,
``VirtualPrime`` creates the veth pair (the master end stays here), gives the loopback interface a
multicast route for the CAN bus, and starts the virtual Prime process on the other end.

The part of a run that talks to the world rather than to the robot (the ROS 2 node) opens its sockets inside
``host_network()``: as root, the command keeps a handle on the host's network namespace across the re-exec,
and that block (with the threads it starts) runs in it, so the node is on the host's ROS 2 graph while the
robot stays private. Without root that is impossible (a user namespace may not enter the host's network
namespace) and the block stays inside.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import subprocess
import sys
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict, Unpack, cast

from humanoid_prime.drivers.erob.objects import BUS_GAIN_GATE, POS_LOOP_GAIN, VEL_LOOP_GAIN
from humanoid_prime.errors import PrimeError
from humanoid_prime.runtime.socket import SOCKET_ENV, default_socket_path
from humanoid_prime.virtual.netns import EmulatedRing, EmulationUnavailable, ip, netns_unavailable_reason
from humanoid_prime.virtual.ring.control import RingControl
from humanoid_prime.virtual.ring.options import RingSettings

if TYPE_CHECKING:
    from humanoid_prime.runtime.session import BringupOptions
    from humanoid_prime.virtual.prime import SitoFaults
    from humanoid_prime.virtual.ring.server import SdoLogEntry

PRIVATE_NETNS_MARK = "PRIME_PRIVATE_NETNS"
HOST_NETNS_FD = "PRIME_HOST_NETNS_FD"  # a descriptor of the host's network namespace, kept across the re-exec
CLONE_NEWNET = 0x40000000  # <sched.h>
CAN_INTERFACE = "udp_multicast"
CAN_CHANNEL = "239.74.163.2"  # python-can's default IPv4 group; private to the namespace


def in_private_netns() -> bool:
    return os.environ.get(PRIVATE_NETNS_MARK) == "1"


def enter_private_netns(argv: Sequence[str] | None = None) -> None:
    """Return at once when already inside; otherwise replace this process by the same command (or ``argv``)
    run in a fresh network namespace. Raises EmulationUnavailable with the reason when that cannot work."""
    if in_private_netns():
        return
    reason = netns_unavailable_reason()
    if reason is not None and os.geteuid() == 0:
        raise EmulationUnavailable(reason)
    args = [sys.executable, *sys.orig_argv[1:]] if argv is None else list(argv)
    os.environ[PRIVATE_NETNS_MARK] = "1"
    os.environ.setdefault(SOCKET_ENV, str(default_socket_path()))  # the user's path, not root-of-the-namespace's
    sys.stdout.flush()
    sys.stderr.flush()
    unshare = ["unshare", "-n"] if os.geteuid() == 0 else ["unshare", "-rn"]
    if os.geteuid() == 0:
        host = os.open("/proc/self/ns/net", os.O_RDONLY)
        os.set_inheritable(host, True)
        os.environ[HOST_NETNS_FD] = str(host)
    try:
        os.execvp(unshare[0], [*unshare, "--", *args])
    except OSError as exc:
        raise EmulationUnavailable(f"cannot run `{' '.join(unshare)}`: {exc.strerror}") from None


@contextlib.contextmanager
def host_network() -> Iterator[bool]:
    """Run the block, in this thread and the threads it starts, in the host's network namespace when this
    process is a private-namespace run that kept a handle on it (as root); yields whether it is on the host.
    Sockets opened in the block stay in the host's namespace after it."""
    handle = os.environ.get(HOST_NETNS_FD, "") if in_private_netns() else ""
    if not handle.isdigit():
        yield False
        return
    libc = ctypes.CDLL(None, use_errno=True)
    private = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
    try:
        if libc.setns(int(handle), CLONE_NEWNET) != 0:
            yield False
            return
        try:
            yield True
        finally:
            if libc.setns(private, CLONE_NEWNET) != 0:  # the robot's side of the run must stay private
                raise EmulationUnavailable(f"cannot return to the emulation's network namespace: "
                                           f"{os.strerror(ctypes.get_errno())}")
    finally:
        os.close(private)


class PrimeControl(RingControl):
    """The virtual Prime's control channel: the ring's operations and the whole robot's (``virtual/prime.py``)."""

    def joints(self) -> dict[str, float]:
        """Every joint's true angle (description frame, rad)."""
        return cast("dict[str, float]", self.call("joints"))  # as ``_op_joints`` sends it

    def push(self, joint: str, torque_nm: float) -> None:
        """A constant external torque on ``joint`` (a test load; 0 takes it off)."""
        self.call("push", joint=joint, torque_nm=torque_nm)

    def hand(self, joint: str, speed_rad_s: float, force_nm: float) -> None:
        """An operator's hand moves ``joint`` at ``speed_rad_s`` pushing with at most ``force_nm`` (0: lets go)."""
        self.call("hand", joint=joint, speed_rad_s=speed_rad_s, force_nm=force_nm)

    def gravity(self, enabled: bool) -> list[float]:
        """Gravity in the plant on or off; the gravity vector now."""
        return cast("list[float]", self.call("gravity", enabled=enabled))  # as ``_op_gravity`` sends it

    def sito(self, joint: str, *, silent: bool | None = None, drop_fraction: float | None = None,
             garbage: bool | None = None, late_s: float | None = None) -> SitoFaults:
        """Faults of one wrist motor (None: as they are); the motor's faults now."""
        return cast("SitoFaults", self.call("sito", joint=joint, silent=silent, drop_fraction=drop_fraction,
                                            garbage=garbage, late_s=late_s))  # as ``_op_sito`` sends it

    def truth(self) -> dict[str, dict[str, float]]:
        """The wiring directions and factory offsets the virtual robot was given, per joint."""
        return cast("dict[str, dict[str, float]]", self.call("truth"))  # as ``_op_truth`` sends it


class VirtualPrime(EmulatedRing):
    """The virtual Prime process on one end of a veth pair, both ends in this (private) namespace; a
    context manager.

    ``master_interface`` is the EtherCAT interface to open; ``can_interface``/``can_channel`` the python-can
    bus of the Sito motors; ``control`` a PrimeControl.
    """

    isolate_emulator = False  # the CAN bus is multicast on this namespace's loopback: share the namespace
    client = PrimeControl

    def __init__(self, *, hardware_file: str | Path | None = None, truth_file: str | Path | None = None,
                 pose: Mapping[str, float] | None = None, startup_timeout_s: float = 20.0,
                 avoid_cpu: int | None = None, **options: Unpack[RingSettings]) -> None:
        super().__init__(startup_timeout_s=startup_timeout_s, avoid_cpu=avoid_cpu, **options)
        self.hardware_file = hardware_file
        self.truth_file = truth_file
        self.pose = dict(pose or {})
        self.can_interface = CAN_INTERFACE
        self.can_channel = CAN_CHANNEL

    def wire_into(self, options: BringupOptions) -> None:
        """Point a run's options at this virtual Prime's buses: its EtherCAT interface and the Sito motors' bus."""
        options.interface = self.master_interface
        options.can_interface, options.can_channel = self.can_interface, self.can_channel

    @property
    def control(self) -> PrimeControl:
        control = super().control
        assert isinstance(control, PrimeControl)  # ``client``
        return control

    def start(self) -> None:
        if not in_private_netns():
            raise EmulationUnavailable("the virtual Prime runs only inside a private network namespace "
                                       "(call enter_private_netns() first)")
        super().start()

    def prepare_namespace(self) -> None:
        ip("link", "set", "lo", "up")
        ip("link", "set", "lo", "multicast", "on")
        result = subprocess.run(["ip", "route", "add", "224.0.0.0/4", "dev", "lo"], capture_output=True, text=True)
        if result.returncode != 0 and "File exists" not in result.stderr:
            raise EmulationUnavailable(f"cannot route multicast on lo: {result.stderr.strip()}")

    def emulator_command(self, control_path: str, parent_fd: int) -> list[str]:
        command = [sys.executable, "-m", "humanoid_prime.virtual", "--iface", self.emulator_interface,
                   "--control", control_path, "--parent-fd", str(parent_fd), "--can-interface", self.can_interface,
                   "--can-channel", self.can_channel, *self.options.to_args()]
        if self.hardware_file is not None:
            command += ["--hardware", str(self.hardware_file)]
        if self.truth_file is not None:
            command += ["--truth", str(self.truth_file)]
        if self.pose:
            command += ["--pose", ",".join(f"{j}={v!r}" for j, v in self.pose.items())]
        return command


EMULATOR_STAGE = "virtual prime"  # the start-up stage of a run that starts the emulated robot


def attach_virtual_prime(stack: contextlib.ExitStack, *, hardware_file: str | Path | None = None,
                         truth_file: str | Path | None = None, ring_options: RingSettings | None = None,
                         record: EmulatorRecord | None = None, avoid_cpu: int | None = None) -> VirtualPrime:
    """Start the virtual Prime (robot at the demonstration's start pose) on ``stack``. With ``record``, what
    the drives themselves recorded (final state, gain-register writes) is put there at teardown, after
    everything entered on ``stack`` later has been closed (gate reset, drives disabled). With ``avoid_cpu``
    (the control loop's CPU) the emulated robot runs on the other CPUs: on the robot, the drives do not share
    the loop's core either."""
    from humanoid_prime.sim.demo import START_POSE

    virtual = stack.enter_context(VirtualPrime(hardware_file=hardware_file, truth_file=truth_file, pose=START_POSE,
                                               avoid_cpu=avoid_cpu, **(ring_options or {})))
    if record is not None:
        stack.callback(_record_emulator, virtual, record)
    return virtual


_POLICIES = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_FIFO: "SCHED_FIFO", os.SCHED_RR: "SCHED_RR",
             os.SCHED_BATCH: "SCHED_BATCH", os.SCHED_IDLE: "SCHED_IDLE"}


class Scheduling(TypedDict):
    cpus: list[int]
    policy: str  # SCHED_OTHER, SCHED_FIFO, ...
    priority: int


class SlaveRecord(TypedDict):
    """One drive at the end of a run, with its gain registers."""

    position: int
    al_state: str
    state: str
    mailbox_faults: int
    error_history: list[int]
    gate: int
    pos_reg: int
    vel_reg: int
    integral: int


class EmulatorRecord(TypedDict, total=False):
    """What the emulated drives recorded of a run (``attach_virtual_prime(record=...)``), filled at teardown."""

    process: Scheduling
    slaves: list[SlaveRecord]
    sdo_log: list[SdoLogEntry]
    joints: dict[str, float]  # the true joint angles when the loop ended (``prime bringup --emulate``)


def scheduling(pid: int) -> Scheduling:
    """The CPUs, policy and real-time priority of process ``pid``'s main thread, read from the kernel."""
    policy = os.sched_getscheduler(pid)
    return {"cpus": sorted(os.sched_getaffinity(pid)), "policy": _POLICIES.get(policy, str(policy)),
            "priority": os.sched_getparam(pid).sched_priority}


_GAIN_OBJECTS = {POS_LOOP_GAIN[0], VEL_LOOP_GAIN[0], BUS_GAIN_GATE[0]}


def _record_emulator(virtual: VirtualPrime, record: EmulatorRecord) -> None:
    """Where the emulator ran (as the kernel has it), the drives' final state and their log of gain-register
    writes, as the emulator saw them."""
    if virtual.pid is not None:
        with contextlib.suppress(OSError):  # the emulator is already gone: its problems say why
            record["process"] = scheduling(virtual.pid)
    with contextlib.suppress(PrimeError):
        record["slaves"] = [{"position": s["position"], "al_state": s["al_state"], "state": s["drive"]["state"],
                             "mailbox_faults": s["mailbox_faults"], "error_history": s["drive"]["error_history"],
                             "gate": s["drive"]["gate"], "pos_reg": s["drive"]["pos_reg"],
                             "vel_reg": s["drive"]["vel_reg"], "integral": s["drive"]["integral"]}
                            for s in virtual.control.status()]
        record["sdo_log"] = [e for e in virtual.control.sdo_log() if e["index"] in _GAIN_OBJECTS]
