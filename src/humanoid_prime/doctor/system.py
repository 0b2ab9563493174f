"""The kernel's own files that the doctor reads, under a root folder: ``/`` on the robot, a fake tree in the tests.

Every reader returns what is there, or None / empty where the file is missing or unreadable: what that means is
the checks' business. Nothing here writes.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

CAP_NET_ADMIN = 12
CAP_NET_RAW = 13
CAP_IPC_LOCK = 14
CAP_SYS_NICE = 23
UNLIMITED = -1
Json = dict[str, object]  # one object of a JSON answer (``ip -json``, a run's summary)


def member(value: object, *keys: str) -> Json:
    """The object at ``keys`` inside ``value``, or an empty one where any step is missing or no object."""
    for key in keys:
        value = value.get(key) if isinstance(value, dict) else None
    return value if isinstance(value, dict) else {}


def strings(value: object) -> list[str]:
    """A JSON list of strings (e.g. an interface's flags); anything else as none."""
    return [v for v in value if isinstance(v, str)] if isinstance(value, list) else []


def parse_cpu_list(text: str) -> set[int]:
    """``0-2,5`` (the kernel's cpulist format) -> {0, 1, 2, 5}; '' -> empty."""
    cpus: set[int] = set()
    for part in text.strip().split(","):
        if not part:
            continue
        low, _, high = part.partition("-")
        cpus.update(range(int(low), int(high or low) + 1))
    return cpus


def cpu_list(cpus: set[int] | list[int]) -> str:
    """{0, 1, 2, 5} -> ``0-2,5``."""
    ordered = sorted(cpus)
    runs: list[list[int]] = []
    for cpu in ordered:
        if runs and cpu == runs[-1][1] + 1:
            runs[-1][1] = cpu
        else:
            runs.append([cpu, cpu])
    return ",".join(f"{a}-{b}" if b > a else str(a) for a, b in runs)


@dataclass(frozen=True)
class Nic:
    """One network interface as the kernel reports it (``nic_state``)."""

    name: str
    exists: bool
    up: bool = False  # administratively up (IFF_UP)
    operstate: str = ""
    carrier: bool | None = None  # None: the kernel does not say (the interface is down)
    speed_mbps: int | None = None  # None: not reported (down, or a virtual NIC)
    duplex: str = ""
    ifindex: int | None = None


@dataclass(frozen=True)
class Limit:
    soft: int  # UNLIMITED (-1) for unlimited
    hard: int


class System:
    """Reads under ``root``; ``pid`` names the process whose status and limits are read ('self' by default)."""

    def __init__(self, root: str | Path = "/", pid: str = "self") -> None:
        self.root = Path(root)
        self.pid = pid

    def read(self, relative: str) -> str | None:
        try:
            return (self.root / relative).read_text()
        except (OSError, UnicodeDecodeError):
            return None

    def value(self, relative: str) -> str | None:
        text = self.read(relative)
        return None if text is None else text.strip()

    def integer(self, relative: str) -> int | None:
        text = self.value(relative)
        try:
            return None if text is None else int(text, 0)
        except ValueError:
            return None

    # ---------------------------------------------------------------------------------------------- network
    def link_speed(self, name: str, ifindex: int | None) -> tuple[int | None, str]:
        """(Mbit/s, duplex) of interface ``name`` from /sys/class/net, where that shows the same interface (its
        ifindex agrees): a process in a network namespace of its own sees the sysfs of the one that mounted it."""
        base = f"sys/class/net/{name}"
        if not name or "/" in name or ifindex is None or self.integer(f"{base}/ifindex") != ifindex:
            return None, ""
        speed = self.integer(f"{base}/speed")  # unreadable while down, -1 where the driver knows none
        return (speed if speed is not None and speed > 0 else None), self.value(f"{base}/duplex") or ""

    def packet_sockets(self, ifindex: int) -> set[str]:
        """Socket inodes (``socket:[N]``) of the raw packet sockets bound to interface ``ifindex``."""
        text = self.read("proc/net/packet") or ""
        inodes = set()
        for line in text.splitlines()[1:]:  # sk RefCnt Type Proto Iface R Rmem User Inode
            fields = line.split()
            with contextlib.suppress(IndexError, ValueError):
                if int(fields[4]) == ifindex:
                    inodes.add(f"socket:[{fields[8]}]")
        return inodes

    def socket_holders(self, inodes: set[str]) -> dict[str, set[tuple[int, str]]]:
        """Each of these sockets -> the processes (pid, command name) that hold it; none where no process this user
        may look into holds it (the kernel's own, an IgH master's generic driver, or another user's)."""
        holders: dict[str, set[tuple[int, str]]] = {inode: set() for inode in inodes}
        if not inodes:
            return holders
        with contextlib.suppress(OSError):
            for entry in (self.root / "proc").iterdir():
                if not entry.name.isdigit():
                    continue
                with contextlib.suppress(OSError):
                    for fd in (entry / "fd").iterdir():
                        with contextlib.suppress(OSError):
                            target = os.readlink(fd)
                            if target in holders:
                                holders[target].add((int(entry.name), self.value(f"proc/{entry.name}/comm") or "?"))
        return holders

    # ---------------------------------------------------------------------------------------------- process
    def capabilities(self) -> int | None:
        """The effective capability set (``CapEff`` of /proc/PID/status)."""
        for line in (self.read(f"proc/{self.pid}/status") or "").splitlines():
            if line.startswith("CapEff:"):
                with contextlib.suppress(ValueError):
                    return int(line.split()[1], 16)
        return None

    def uid(self) -> int | None:
        """The effective user id (``Uid`` of /proc/PID/status)."""
        for line in (self.read(f"proc/{self.pid}/status") or "").splitlines():
            if line.startswith("Uid:"):
                with contextlib.suppress(ValueError, IndexError):
                    return int(line.split()[2])
        return None

    def limit(self, name: str) -> Limit | None:
        """A resource limit as /proc/PID/limits lists it (``Max realtime priority``, ``Max locked memory``); the
        same values getrlimit returns."""
        for line in (self.read(f"proc/{self.pid}/limits") or "").splitlines():
            if line.startswith(name):
                fields = line[len(name):].split()
                with contextlib.suppress(ValueError, IndexError):
                    return Limit(*(UNLIMITED if f == "unlimited" else int(f) for f in fields[:2]))
        return None

    # ----------------------------------------------------------------------------------------------- kernel
    def kernel_version(self) -> str:
        """What ``uname -v`` prints (its build flags, PREEMPT_RT among them)."""
        return self.value("proc/sys/kernel/version") or ""

    def realtime_flag(self) -> bool:
        return self.value("sys/kernel/realtime") == "1"

    def governors(self) -> dict[int, str]:
        """CPU -> its cpufreq scaling governor (empty where the kernel scales no frequency, as in many VMs)."""
        found = {}
        cpus = self.root / "sys/devices/system/cpu"
        with contextlib.suppress(OSError):
            for entry in cpus.iterdir():
                if entry.name.startswith("cpu") and entry.name[3:].isdigit():
                    governor = self.value(f"sys/devices/system/cpu/{entry.name}/cpufreq/scaling_governor")
                    if governor:
                        found[int(entry.name[3:])] = governor
        return dict(sorted(found.items()))

    def isolated_cpus(self) -> set[int]:
        return parse_cpu_list(self.value("sys/devices/system/cpu/isolated") or "")

    def online_cpus(self) -> set[int]:
        return parse_cpu_list(self.value("sys/devices/system/cpu/online") or "")

    def interrupts_of(self, interface: str) -> dict[int, set[int] | None]:
        """IRQ -> CPUs it may run on, for every interrupt line /proc/interrupts names after ``interface`` (its name,
        or its name and a queue suffix such as ``-TxRx-0``); None where the affinity is unreadable."""
        found: dict[int, set[int] | None] = {}
        for line in (self.read("proc/interrupts") or "").splitlines()[1:]:
            number, _, rest = line.strip().partition(":")
            if not number.isdigit():
                continue
            names = rest.split()
            if any(n == interface or n.startswith(f"{interface}-") for n in names):
                affinity = self.value(f"proc/irq/{number}/smp_affinity_list")
                found[int(number)] = None if affinity is None else parse_cpu_list(affinity)
        return found


def ip_link(name: str) -> tuple[bool, Json | None]:
    """(the interface exists, its entry of ``ip -details -statistics -json link show``; None if unreadable). Over
    netlink, so it answers for this process's network namespace, wherever sysfs was mounted."""
    try:
        proc = subprocess.run(["ip", "-details", "-statistics", "-json", "link", "show", "dev", name],
                              capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.TimeoutExpired):
        return True, None
    if proc.returncode != 0:
        return "does not exist" not in proc.stderr, None
    try:
        entries = json.loads(proc.stdout)
    except ValueError:
        return True, None
    return True, entries[0] if isinstance(entries, list) and entries and isinstance(entries[0], dict) else None


def ip_links() -> list[str]:
    """The names of this network namespace's interfaces."""
    try:
        proc = subprocess.run(["ip", "-json", "link", "show"], capture_output=True, text=True, timeout=5)
        entries = json.loads(proc.stdout) if proc.returncode == 0 else []
    except (OSError, subprocess.TimeoutExpired, ValueError):
        return []
    names = (e.get("ifname") for e in entries if isinstance(e, dict)) if isinstance(entries, list) else ()
    return sorted(n for n in names if isinstance(n, str))


def nic_state(name: str, exists: bool, link: Json | None, system: System) -> Nic:
    """``name`` as ``ip`` reports it (administratively up: flag UP; carrier: LOWER_UP, or NO-CARRIER), with its
    speed and duplex from sysfs."""
    if not exists:
        return Nic(name, exists=False)
    if link is None:
        return Nic(name, exists=True)
    flags = strings(link.get("flags"))
    carrier = True if "LOWER_UP" in flags else False if "NO-CARRIER" in flags else None
    index = link.get("ifindex")
    ifindex = index if isinstance(index, int) else None
    speed, duplex = system.link_speed(name, ifindex)
    return Nic(name, exists=True, up="UP" in flags, operstate=str(link.get("operstate") or ""),
               carrier=carrier if "UP" in flags else None, speed_mbps=speed, duplex=duplex, ifindex=ifindex)
