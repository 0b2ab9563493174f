"""Run the emulated eRob ring on one end of a veth pair, the other end left to the master.

``EmulatedRing`` creates the pair, starts the emulator in a private network namespace of its own (the
emulator end is moved there), and exposes ``master_interface`` (open it with the master) and ``control``
(a RingControl). It cleans up on every exit path: leaving the ``with`` block normally or by exception or
KeyboardInterrupt stops the emulator and deletes the pair; if this process dies outright, the emulator
sees its pipe from this process close and exits, its namespace disappears and the pair with it.

Creating a veth pair and a namespace needs CAP_NET_ADMIN and CAP_SYS_ADMIN here: run as root, or run
the whole command inside a user and network namespace (``unshare -rn CMD``, or ``reexec_in_user_netns``),
where the process is root of its own namespaces. ``netns_unavailable_reason()`` says which applies.

    with EmulatedRing(slaves=10, dc_lock_cycles=20) as ring:
        master = pysoem.Master()
        master.open(ring.master_interface)
        ...
        ring.control.status()
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import itertools
import os
import select
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn, Self, Unpack

from humanoid_prime.drivers.ethercat.wire import ETHERTYPE, Command
from humanoid_prime.errors import PrimeError
from humanoid_prime.virtual.ring.control import ControlError, RingControl
from humanoid_prime.virtual.ring.frames import Datagram, build_frame, parse_frame
from humanoid_prime.virtual.ring.options import RingOptions, RingSettings
from humanoid_prime.virtual.ring.server import disable_ipv6

_REEXEC_MARK = "PRIME_EMULATION_USERNS"
_counter = itertools.count()


class EmulationUnavailable(PrimeError):
    """This machine or process cannot host the emulated ring (no privileges, no iproute2)."""


@functools.lru_cache(maxsize=1)
def netns_unavailable_reason() -> str | None:
    """None when this process can create a veth pair and a network namespace; otherwise one line saying
    why not and what to do."""
    for tool in ("ip", "unshare"):
        if shutil.which(tool) is None:
            return f"the `{tool}` command is missing (install iproute2 / util-linux)"
    probe = subprocess.run(["unshare", "--net", "ip", "link", "add", "prime-probe0", "type", "veth", "peer",
                            "name", "prime-probe1"], capture_output=True, text=True, timeout=10)
    if probe.returncode == 0:
        return None
    if os.geteuid() != 0:
        userns = subprocess.run(["unshare", "-rn", "true"], capture_output=True, timeout=10)
        if userns.returncode == 0:
            return "not root: run as root or inside a user+network namespace (prefix the command with `unshare -rn`)"
        return "not root and user namespaces are disabled here: run as root"
    return f"cannot create a veth pair in a network namespace: {probe.stderr.strip() or 'unknown error'}"


def reexec_in_user_netns(argv: Sequence[str] | None = None) -> NoReturn:
    """Replace this process by ``argv`` (default: this very command line) run under ``unshare -rn``, as
    root of a new user and network namespace; only that namespace's interfaces are visible there.
    Raises EmulationUnavailable when already re-executed once (user namespaces did not give the rights)."""
    if os.environ.get(_REEXEC_MARK):
        raise EmulationUnavailable("already inside `unshare -rn` and still unable to create a veth pair")
    args = [sys.executable, *sys.orig_argv[1:]] if argv is None else list(argv)
    os.environ[_REEXEC_MARK] = "1"
    os.execvp("unshare", ["unshare", "-rn", "--", *args])


def ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    if result.returncode != 0:
        raise EmulationUnavailable(f"`ip {' '.join(args)}` failed: {result.stderr.strip()}")


class EmulatedRing:
    """An emulated eRob ring on a veth pair; a context manager. Options are RingOptions fields
    (``slaves``, ``dc_lock_cycles``, ``mailbox_latency_s``, ...). With ``avoid_cpu``, the emulator process runs
    on every CPU this process may use but that one (the control loop's, with ``--cpu``), where there is another."""

    client: type[RingControl] = RingControl  # of the control channel

    def __init__(self, *, startup_timeout_s: float = 10.0, avoid_cpu: int | None = None,
                 **options: Unpack[RingSettings]) -> None:
        self.options = RingOptions(**options)
        self.options.check()
        self.startup_timeout_s = startup_timeout_s
        others = sorted(set(os.sched_getaffinity(0)) - {avoid_cpu}) if avoid_cpu is not None else []
        self.emulator_cpus: list[int] | None = others or None
        tag = f"{os.getpid()}x{next(_counter)}"
        self.master_interface = f"ecm{tag}"
        self.emulator_interface = f"ecs{tag}"
        self._control: RingControl | None = None
        self._process: subprocess.Popen[bytes] | None = None
        self._workdir: Path | None = None
        self._pair_created = False
        self._lifeline: int | None = None  # write end of the pipe whose closing tells the emulator to exit

    @property
    def control(self) -> RingControl:
        if self._control is None:
            raise EmulationUnavailable("the emulated ring is not running (use it inside `with EmulatedRing(...)`)")
        return self._control

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    @property
    def running(self) -> bool:
        """The emulator process is alive."""
        return self._process is not None and self._process.poll() is None

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        reason = netns_unavailable_reason()
        if reason is not None:
            raise EmulationUnavailable(reason)
        atexit.register(self.close)
        try:
            self._start()
        except BaseException:
            self.close()
            raise

    # Subclasses (the whole virtual Prime) change what runs and where, through these three.
    isolate_emulator = True  # the emulator end goes into a namespace of its own; False: both ends stay here

    def emulator_command(self, control_path: str, parent_fd: int) -> list[str]:
        """The emulator's command line; it must serve ``self.emulator_interface`` and exit when
        ``parent_fd`` closes."""
        return [sys.executable, "-m", "humanoid_prime.virtual.ring", "--iface", self.emulator_interface,
                "--control", control_path, "--parent-fd", str(parent_fd),
                "--wait-iface", str(self.startup_timeout_s), *self.options.to_args()]

    def prepare_namespace(self) -> None:
        """Set up this namespace before the pair is created (nothing for a bare ring)."""

    def _start(self) -> None:
        self._workdir = Path(tempfile.mkdtemp(prefix="prime-ec-"))
        control_path = str(self._workdir / "control.sock")
        self.prepare_namespace()
        ip("link", "add", self.master_interface, "type", "veth", "peer", "name", self.emulator_interface)
        self._pair_created = True
        disable_ipv6(self.master_interface)  # the emulator end is brought up by the emulator itself
        lifeline_read, self._lifeline = os.pipe()
        command = self.emulator_command(control_path, lifeline_read)
        if self.isolate_emulator:
            command = ["unshare", "--net", "--", *command]
        if self.emulator_cpus is not None:  # set before the exec, so every thread it starts inherits it
            command = ["taskset", "--cpu-list", ",".join(map(str, self.emulator_cpus)), *command]
        log = open(self._workdir / "emulator.log", "wb")  # noqa: SIM115 - handed to the child
        with log:
            # Its own session: a Ctrl-C at the terminal stops the master's loop, not the emulated hardware,
            # which must stay up while the master resets gains and disables the drives.
            self._process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                             pass_fds=(lifeline_read,), start_new_session=True)
        os.close(lifeline_read)
        deadline = time.monotonic() + self.startup_timeout_s
        if self.isolate_emulator:
            own_namespace = os.readlink("/proc/self/ns/net")
            while True:
                self._check_alive()
                with contextlib.suppress(OSError):
                    if os.readlink(f"/proc/{self._process.pid}/ns/net") != own_namespace:
                        break
                self._check_deadline(deadline, "enter its network namespace")
                time.sleep(0.002)
            ip("link", "set", self.emulator_interface, "netns", str(self._process.pid))
        ip("link", "set", self.master_interface, "up")
        while self._control is None:
            self._check_alive()
            if os.path.exists(control_path):
                with contextlib.suppress(ControlError):
                    self._control = self.client(control_path)
            if self._control is None:
                self._check_deadline(deadline, "open its control socket")
                time.sleep(0.005)
        self._control.ping()
        self._wait_for_frames(deadline)

    def _wait_for_frames(self, deadline: float) -> None:
        """Send a broadcast read on the master end until the ring answers with every slave counted."""
        with socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0) as raw:  # EtherCAT once bound: this ring's only
            raw.bind((self.master_interface, ETHERTYPE))
            probe = build_frame([Datagram(Command.BRD, b"\x00\x00", index=0xA5)])
            while True:
                raw.send(probe)
                ready, _, _ = select.select([raw], [], [], 0.05)
                if ready:
                    reply = parse_frame(raw.recv(2048))
                    if reply and reply[0].index == 0xA5 and reply[0].wkc == self.options.slaves:
                        return
                self._check_alive()
                self._check_deadline(deadline, "answer frames")

    def _check_alive(self) -> None:
        if self._process is not None and self._process.poll() is not None:
            raise EmulationUnavailable(f"the emulator exited with status {self._process.returncode}: "
                                       f"{self._log_tail()}")

    def _check_deadline(self, deadline: float, what: str) -> None:
        if time.monotonic() > deadline:
            raise EmulationUnavailable(f"the emulator did not {what} within {self.startup_timeout_s:g} s: "
                                       f"{self._log_tail()}")

    def _log_tail(self) -> str:
        if self._workdir is None:
            return ""
        with contextlib.suppress(OSError):
            text = (self._workdir / "emulator.log").read_text(errors="replace").strip()
            return text.splitlines()[-1] if text else "(no output)"
        return "(no log)"

    def close(self) -> None:
        """Stop the emulator and delete the pair and the working directory; safe to call twice."""
        atexit.unregister(self.close)
        if self._control is not None:
            with contextlib.suppress(Exception):
                self._control.close()
            self._control = None
        if self._process is not None:
            if self._process.poll() is None:
                self._process.terminate()
                try:
                    self._process.wait(timeout=3)
                except subprocess.TimeoutExpired:
                    self._process.kill()
                    self._process.wait()
            self._process = None
        if self._lifeline is not None:
            os.close(self._lifeline)
            self._lifeline = None
        if self._pair_created:
            subprocess.run(["ip", "link", "del", self.master_interface], capture_output=True, timeout=10)
            self._pair_created = False
        if self._workdir is not None:
            shutil.rmtree(self._workdir, ignore_errors=True)
            self._workdir = None
