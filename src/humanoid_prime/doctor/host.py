"""The host's checks: the ring's NIC and who else uses it, the rights a real-time EtherCAT master needs, and the
kernel's real-time setup. Each check is a pure function of what was read (``system.py``, ``ip``, a capture), so
the tests give it a fake /sys and /proc tree.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import socket
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field

from humanoid_prime.doctor.report import Check, failed, not_run, passed, warned
from humanoid_prime.doctor.system import (
    CAP_IPC_LOCK,
    CAP_NET_RAW,
    CAP_SYS_NICE,
    UNLIMITED,
    Limit,
    Nic,
    System,
    cpu_list,
)
from humanoid_prime.runtime.realtime import FIFO_PRIORITY

GROUP = "host"
ETHERTYPE_ECAT = 0x88A4
ETHERTYPE_VLAN = 0x8100
ETH_P_ALL = 0x0003
PACKET_OUTGOING = 4
ETHERCAT_MBPS = 100  # an ESC's port is 100BASE-TX
LISTEN_S = 1.0  # how long the ring's NIC is watched for frames that are no EtherCAT
ETHERTYPES = {0x0800: "IPv4", 0x0806: "ARP", 0x86DD: "IPv6", 0x88CC: "LLDP", 0x8035: "RARP", 0x88F7: "PTP"}


def has(capabilities: int | None, capability: int) -> bool:
    return capabilities is not None and bool(capabilities >> capability & 1)


def python_binary() -> str:
    """The interpreter file a capability would be granted to (setcap needs the real file, not a venv link)."""
    return os.path.realpath(sys.executable)


# ----------------------------------------------------------------------------------------------------- the NIC
def nic_checks(nic: Nic, key: str, known: list[str]) -> list[Check]:
    """The NIC exists, is up, has carrier, and links at EtherCAT's speed; ``key`` says where its name came from."""
    name = nic.name
    if not nic.exists:
        others = ", ".join(n for n in known if n != "lo") or "none"
        return [failed(GROUP, "nic", f"no network interface {name!r} ({key}); this machine has: {others}",
                       f"set {key} to the NIC the ring is cabled to (`ip -br link` lists them)"),
                *(not_run(GROUP, check, f"no interface {name!r}") for check in ("nic.up", "nic.carrier", "nic.speed"))]
    checks = [passed(GROUP, "nic", f"{name} exists ({key})")]
    if not nic.up:
        checks.append(failed(GROUP, "nic.up", f"{name} is down (operstate {nic.operstate or 'unknown'})",
                             f"sudo ip link set {name} up"))
        checks += [not_run(GROUP, "nic.carrier", f"{name} is down"), not_run(GROUP, "nic.speed", f"{name} is down")]
        return checks
    checks.append(passed(GROUP, "nic.up", f"{name} is up"))
    if nic.carrier is False:
        checks.append(failed(GROUP, "nic.carrier", f"no carrier on {name}: nothing answers on its cable",
                             f"check the cable from {name} to the first drive's IN port and that the drives have "
                             f"power; `cat /sys/class/net/{name}/carrier` reads 1 once the link is there"))
        checks.append(not_run(GROUP, "nic.speed", f"no link on {name}"))
        return checks
    if nic.carrier is None:
        checks.append(warned(GROUP, "nic.carrier", f"{name} does not report carrier (operstate {nic.operstate})"))
    else:
        checks.append(passed(GROUP, "nic.carrier", f"carrier on {name}"))
    checks.append(speed_check(nic))
    return checks


def speed_check(nic: Nic) -> Check:
    name, speed = nic.name, nic.speed_mbps
    duplex = f" {nic.duplex} duplex" if nic.duplex and nic.duplex != "unknown" else ""
    if speed is None:
        return warned(GROUP, "nic.speed", f"{name} reports no link speed (a virtual NIC, or its driver does not say); "
                                          f"an eRob links at {ETHERCAT_MBPS} Mbit/s")
    if nic.duplex == "half":
        return failed(GROUP, "nic.speed", f"{name} links at {speed} Mbit/s half duplex; EtherCAT needs full duplex",
                      f"let {name} autonegotiate: sudo ethtool -s {name} autoneg on")
    if speed < ETHERCAT_MBPS:
        return failed(GROUP, "nic.speed", f"{name} links at {speed} Mbit/s{duplex}, below EtherCAT's "
                                          f"{ETHERCAT_MBPS} Mbit/s",
                      f"sudo ethtool -s {name} autoneg on; check the cable")
    if speed > ETHERCAT_MBPS:
        return warned(GROUP, "nic.speed", f"{name} links at {speed} Mbit/s{duplex}; an eRob's port links at "
                                          f"{ETHERCAT_MBPS}, so something else (a switch?) is on the cable",
                      f"cable {name} straight to the first drive's IN port")
    return passed(GROUP, "nic.speed", f"{name} links at {speed} Mbit/s{duplex}")


def addresses(interface: str) -> list[str] | None:
    """The IP addresses on ``interface`` (``ip -json addr``); None where ``ip`` could not tell."""
    try:
        proc = subprocess.run(["ip", "-json", "addr", "show", "dev", interface], capture_output=True, text=True,
                              timeout=5)
        entries = json.loads(proc.stdout) if proc.returncode == 0 else None
    except (OSError, subprocess.TimeoutExpired, ValueError):
        return None
    if not isinstance(entries, list):
        return None
    return [f"{a.get('local')}/{a.get('prefixlen')}" for e in entries for a in e.get("addr_info", [])
            if isinstance(a, dict) and a.get("local")]


def addresses_check(interface: str, found: list[str] | None) -> Check:
    if found is None:
        return not_run(GROUP, "nic.addresses", "`ip -json addr` gave no answer")
    if not found:
        return passed(GROUP, "nic.addresses", f"no IP address on {interface}")
    return warned(GROUP, "nic.addresses",
                  f"{interface} has IP addresses ({', '.join(found)}): the network stack uses the ring's NIC and "
                  "sends on it (DHCP, IPv6 neighbour discovery)",
                  f"sudo ip addr flush dev {interface}; sudo sysctl -w net.ipv6.conf.{interface}.disable_ipv6=1; "
                  f"keep the network manager off it: nmcli device set {interface} managed no")


def sockets_check(interface: str, holders: dict[str, set[tuple[int, str]]], own_pid: int | None = None) -> Check:
    """Raw sockets on the ring's NIC that are not this process's: another master (SOEM, a running prime, an IgH
    master's generic driver) or a capture. A scan beside a running master would take its slaves to INIT."""
    own = os.getpid() if own_pid is None else own_pid
    others = {inode: held for inode, held in holders.items() if not any(pid == own for pid, _ in held)}
    if not others:
        return passed(GROUP, "nic.users", f"no other program has a raw socket on {interface}")
    named = sorted({who for held in others.values() for who in held})
    parts = [f"pid {pid} ({comm})" for pid, comm in named]
    unseen = sum(1 for held in others.values() if not held)
    if unseen:
        parts.append(f"{unseen} socket{'s' if unseen > 1 else ''} of no process this user may see (the kernel's: "
                     "an IgH master's generic driver?)")
    fix = (f"stop it (kill {' '.join(str(pid) for pid, _ in named)})" if named else "stop that master") \
        + ", or give Prime a NIC of its own"
    return failed(GROUP, "nic.users", f"{'; '.join(parts)}: a raw socket on {interface}, a second master or a "
                                      "capture on the ring", fix)


@dataclass
class Traffic:
    """Frames seen on a NIC by a raw socket: (direction, ethertype) -> count; ``seconds`` watched."""

    seconds: float
    frames: Counter[tuple[str, int]] = field(default_factory=Counter)
    ethercat: int = 0

    def foreign(self) -> Counter[tuple[str, int]]:
        return Counter({k: v for k, v in self.frames.items() if k[1] != ETHERTYPE_ECAT})


def watch(interface: str, seconds: float = LISTEN_S) -> Traffic:
    """Every frame on ``interface`` for ``seconds``, both directions (OSError when no raw socket may be opened)."""
    traffic = Traffic(seconds)
    # Opened for no protocol and given every protocol in ``bind``: opened for one, the socket takes it from every NIC
    # until it is bound, and another NIC's frames queued meanwhile would be counted as this one's.
    with socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0) as sock:
        sock.bind((interface, ETH_P_ALL))
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            ready, _, _ = select.select([sock], [], [], left)
            if not ready:
                continue
            with contextlib.suppress(BlockingIOError):
                data, address = sock.recvfrom(65535)
                if len(data) < 14:
                    continue
                ethertype = int.from_bytes(data[12:14], "big")
                if ethertype == ETHERTYPE_VLAN and len(data) >= 18:
                    ethertype = int.from_bytes(data[16:18], "big")
                if ethertype == ETHERTYPE_ECAT:
                    traffic.ethercat += 1
                    continue
                direction = "sent" if address[2] == PACKET_OUTGOING else "received"
                traffic.frames[(direction, ethertype)] += 1
    return traffic


def traffic_check(interface: str, traffic: Traffic) -> Check:
    foreign = traffic.foreign()
    if not foreign:
        return passed(GROUP, "nic.traffic", f"no frame but EtherCAT on {interface} in {traffic.seconds:g} s")
    parts = [f"{count} {ETHERTYPES.get(ethertype, f'0x{ethertype:04X}')} {direction}"
             for (direction, ethertype), count in sorted(foreign.items())]
    sent = any(direction == "sent" for direction, _ in foreign)
    fix = (f"keep this host's network stack off {interface}: nmcli device set {interface} managed no; "
           f"sudo ip addr flush dev {interface}; sudo sysctl -w net.ipv6.conf.{interface}.disable_ipv6=1"
           if sent else f"find what else is on {interface}'s cable (a switch, a PC): the ring takes EtherCAT only")
    return failed(GROUP, "nic.traffic", f"frames that are no EtherCAT on {interface} in {traffic.seconds:g} s: "
                                        f"{', '.join(parts)}; they share the wire with the cycle's frames", fix)


# ---------------------------------------------------------------------------------------------- rights and limits
def raw_socket_check(capabilities: int | None, interface: str) -> Check:
    if capabilities is None:
        return not_run(GROUP, "cap_net_raw", "no CapEff in /proc/self/status")
    if has(capabilities, CAP_NET_RAW):
        return passed(GROUP, "cap_net_raw", "CAP_NET_RAW held: SOEM may open a raw socket")
    return failed(GROUP, "cap_net_raw", f"no CAP_NET_RAW: SOEM cannot open a raw socket on {interface}",
                  f"run as root, or grant it once: sudo setcap cap_net_raw,cap_sys_nice,cap_ipc_lock+ep "
                  f"{python_binary()}")


def _limit_text(limit: Limit, unit: str = "") -> str:
    return "unlimited" if limit.soft == UNLIMITED else f"{limit.soft}{unit}"


def rtprio_check(capabilities: int | None, limit: Limit | None, priority: int = FIFO_PRIORITY) -> Check:
    """SCHED_FIFO at the control loop's priority: CAP_SYS_NICE, or an RLIMIT_RTPRIO that reaches it."""
    if has(capabilities, CAP_SYS_NICE):
        return passed(GROUP, "rtprio", f"CAP_SYS_NICE held: the loop may run at SCHED_FIFO {priority}")
    if limit is not None and (limit.soft == UNLIMITED or limit.soft >= priority):
        return passed(GROUP, "rtprio", f"real-time priority allowed up to {_limit_text(limit)} (ulimit -r): the "
                                       f"loop runs at SCHED_FIFO {priority}")
    allowed = "not readable" if limit is None else _limit_text(limit)
    return failed(GROUP, "rtprio", f"no real-time scheduling: ulimit -r is {allowed}, the loop needs SCHED_FIFO "
                                   f"{priority}",
                  "add `@realtime - rtprio 95` to /etc/security/limits.d/99-prime.conf, put the user in group "
                  "realtime and log in again (or run as root)")


def memlock_check(capabilities: int | None, limit: Limit | None) -> Check:
    """Locking the process's memory (mlockall): CAP_IPC_LOCK, or no RLIMIT_MEMLOCK."""
    if has(capabilities, CAP_IPC_LOCK):
        return passed(GROUP, "memlock", "CAP_IPC_LOCK held: the process may lock its memory")
    if limit is not None and limit.soft == UNLIMITED:
        return passed(GROUP, "memlock", "locked memory unlimited (ulimit -l)")
    allowed = "not readable" if limit is None else f"{limit.soft // 1024} KiB"
    return failed(GROUP, "memlock", f"locked memory limited to {allowed} (ulimit -l): mlockall of the whole process "
                                    "(hundreds of MiB) is refused, so pages the tick uses may be paged out",
                  "add `@realtime - memlock unlimited` to /etc/security/limits.d/99-prime.conf and log in again "
                  "(or run as root)")


# --------------------------------------------------------------------------------------------------- the kernel
def kernel_check(realtime: bool, version: str) -> Check:
    if realtime or "PREEMPT_RT" in version:
        return passed(GROUP, "kernel", f"PREEMPT_RT kernel ({version})")
    return warned(GROUP, "kernel", f"not a PREEMPT_RT kernel (uname -v: {version or 'unreadable'}): wake-ups may "
                                   "come late under load", "boot a PREEMPT_RT kernel (Debian: apt install "
                                                           "linux-image-rt-amd64; Ubuntu: pro enable realtime-kernel)")


def governor_check(governors: dict[int, str]) -> Check:
    if not governors:
        return passed(GROUP, "governor", "the kernel scales no CPU frequency here (no cpufreq): nothing to set")
    slow = {cpu: g for cpu, g in governors.items() if g != "performance"}
    if not slow:
        return passed(GROUP, "governor", f"performance governor on CPUs {cpu_list(list(governors))}")
    by_governor: dict[str, list[int]] = {}
    for cpu, governor in slow.items():
        by_governor.setdefault(governor, []).append(cpu)
    text = "; ".join(f"{g} on CPUs {cpu_list(cpus)}" for g, cpus in sorted(by_governor.items()))
    return warned(GROUP, "governor", f"{text}: a CPU that clocks down wakes the loop late",
                  "sudo cpupower frequency-set -g performance (Debian: linux-cpupower)")


def isolation_check(isolated: set[int]) -> Check:
    if isolated:
        return passed(GROUP, "isolcpus", f"CPUs {cpu_list(isolated)} isolated: run the loop there with --cpu N")
    return warned(GROUP, "isolcpus", "no CPU isolated for the control loop: the scheduler puts other work beside it",
                  "boot with isolcpus=N nohz_full=N rcu_nocbs=N for one CPU N, then run with --cpu N")


def irq_check(interface: str, irqs: dict[int, set[int] | None], isolated: set[int]) -> Check:
    if not irqs:
        return not_run(GROUP, "nic.irq", f"/proc/interrupts names no interrupt after {interface} (a virtual NIC has "
                                         "none; some drivers name theirs after the driver)")
    shown = ", ".join(f"{irq} on CPUs {cpu_list(cpus) if cpus is not None else '?'}" for irq, cpus in irqs.items())
    on_loop = sorted(irq for irq, cpus in irqs.items() if cpus is not None and cpus & isolated)
    if on_loop:
        keep = cpu_list(set().union(*(c for c in irqs.values() if c)) - isolated) or "another CPU"
        return warned(GROUP, "nic.irq", f"{interface}'s interrupts may run on the isolated CPUs "
                                        f"{cpu_list(isolated)} meant for the loop: IRQ {shown}",
                      "; ".join(f"echo {keep} | sudo tee /proc/irq/{irq}/smp_affinity_list" for irq in on_loop)
                      + " (and keep irqbalance from moving them back)")
    where = "off the isolated CPUs" if isolated else "(no CPU is isolated, so none is the loop's)"
    return passed(GROUP, "nic.irq", f"{interface}'s interrupts {where}: IRQ {shown}")


def host_rights(system: System) -> tuple[int | None, list[Check]]:
    """The effective capabilities, and the checks of the rights a real-time master needs beside CAP_NET_RAW."""
    capabilities = system.capabilities()
    return capabilities, [rtprio_check(capabilities, system.limit("Max realtime priority")),
                          memlock_check(capabilities, system.limit("Max locked memory"))]


def kernel_checks(system: System) -> list[Check]:
    return [kernel_check(system.realtime_flag(), system.kernel_version()), governor_check(system.governors()),
            isolation_check(system.isolated_cpus())]
