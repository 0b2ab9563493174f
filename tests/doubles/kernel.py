"""A fake /sys and /proc tree, for the doctor's checks: what a real-time robot computer, or a badly set-up one,
shows, written file by file under a temporary root, and the ``ip -json`` entries of its links."""

from __future__ import annotations

import os
from pathlib import Path

from humanoid_prime.doctor.system import System

ALL_CAPS = 0x1FFFFFFFFFF  # what root holds
LIMITS = """Limit                     Soft Limit           Hard Limit           Units
Max cpu time              unlimited            unlimited            seconds
Max locked memory         {memlock}            {memlock}            bytes
Max realtime priority     {rtprio}             {rtprio}
Max realtime timeout      unlimited            unlimited            us
"""


def write_tree(root: Path, files: dict[str, str]) -> System:
    """Write ``files`` (path under the root -> text; a text starting with '->' makes a symbolic link to the rest)
    and return a System reading them."""
    for relative, text in files.items():
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        if text.startswith("->"):
            os.symlink(text[2:], path)
        else:
            path.write_text(text)
    return System(root)


def process(caps: int, *, memlock: str = "8388608", rtprio: str = "0", uid: int = 1000) -> dict[str, str]:
    """/proc/self/status and /proc/self/limits of a process with effective capabilities ``caps``."""
    return {"proc/self/status": f"Name:\tpython3\nUid:\t{uid}\t{uid}\t{uid}\t{uid}\nCapInh:\t0000000000000000\n"
                                f"CapPrm:\t{caps:016x}\nCapEff:\t{caps:016x}\nCapBnd:\t000001ffffffffff\n",
            "proc/self/limits": LIMITS.format(memlock=memlock, rtprio=rtprio)}


def nic_files(name: str, *, ifindex: int = 3, speed: str = "100\n", duplex: str = "full\n") -> dict[str, str]:
    base = f"sys/class/net/{name}"
    return {f"{base}/ifindex": f"{ifindex}\n", f"{base}/speed": speed, f"{base}/duplex": duplex}


def link(name: str, flags: list[str], *, ifindex: int = 3, operstate: str = "UP", **more: object) -> dict[str, object]:
    """An ``ip -details -statistics -json link show`` entry."""
    return {"ifindex": ifindex, "ifname": name, "flags": flags, "operstate": operstate, **more}


def can_link(name: str, *, state: str = "ERROR-ACTIVE", bitrate: int | None = 1000000, up: bool = True,
             txqlen: int = 1000, berr: tuple[int, int] = (0, 0), xstats: dict[str, int] | None = None,
             errors: tuple[int, int] = (0, 0)) -> dict[str, object]:
    """A SocketCAN link as ``ip -details -statistics -json link show`` reports it (iproute2's iplink_can.c)."""
    info: dict[str, object] = {"state": state, "berr_counter": {"tx": berr[0], "rx": berr[1]}, "restart_ms": 0}
    if bitrate is not None:
        info["bittiming"] = {"bitrate": bitrate, "sample_point": "0.875", "tq": 12, "prop_seg": 34,
                             "phase_seg1": 35, "phase_seg2": 10, "sjw": 1, "brp": 1}
    stats = {"restarts": 0, "bus_error": 0, "arbitration_lost": 0, "error_warning": 0, "error_passive": 0,
             "bus_off": 0, **(xstats or {})}
    flags = ["NOARP", "UP", "LOWER_UP", "ECHO"] if up else ["NOARP", "ECHO"]
    return link(name, flags, operstate="UP" if up else "DOWN", txqlen=txqlen, link_type="can",
                linkinfo={"info_kind": "can", "info_data": info, "info_xstats": stats},
                stats64={"rx": {"bytes": 0, "packets": 0, "errors": errors[0]},
                         "tx": {"bytes": 0, "packets": 0, "errors": errors[1]}})
