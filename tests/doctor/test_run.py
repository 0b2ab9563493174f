"""One doctor run, its kernel files a fake tree: what keeps it off the ring, and what it then says."""

from __future__ import annotations

from pathlib import Path

from doubles.kernel import ALL_CAPS, process, write_tree
from humanoid_prime.config.location import resolve_all
from humanoid_prime.doctor.ethercat import CHECKS
from humanoid_prime.doctor.run import DoctorOptions, run_doctor
from humanoid_prime.doctor.system import CAP_NET_RAW, ip_link


def options(robot, root: Path, interface: str) -> DoctorOptions:
    return DoctorOptions(files=resolve_all(hardware=robot.hardware.path), backends=("ec",), interface=interface,
                         root=root, watch_s=0.05, probe_s=0.05)


def loopback_index() -> int:
    _, entry = ip_link("lo")
    assert entry is not None
    return int(entry["ifindex"])


def test_beside_another_program_s_raw_socket_the_ring_is_not_scanned(robot, tmp_path):
    """A master may be running the ring on that NIC: a scan would take its slaves to INIT."""
    root = tmp_path / "root"
    write_tree(root, {**process(ALL_CAPS, uid=0),
                      "proc/net/packet": "sk RefCnt Type Proto Iface R Rmem User Inode\n"
                                         f"0000000000000000 3 3 0003 {loopback_index()} 1 0 0 990099\n",
                      "proc/4321/comm": "prime\n", "proc/4321/fd/5": "->socket:[990099]"})
    report = run_doctor(options(robot, root, "lo"))
    checks = {c.id: c for c in report.checks}
    assert checks["host.nic.users"].verdict.value == "fail"
    assert checks["host.nic.users"].found.startswith("pid 4321 (prime): a raw socket on lo")
    for name in CHECKS:
        check = checks[f"ethercat.{name}"]
        assert not check.ran and "would take its slaves to INIT" in check.found


def test_without_cap_net_raw_nothing_opens_the_nic(robot, tmp_path):
    root = tmp_path / "root"
    write_tree(root, process(ALL_CAPS & ~(1 << CAP_NET_RAW), uid=0))
    report = run_doctor(options(robot, root, "lo"))
    checks = {c.id: c for c in report.checks}
    assert checks["host.cap_net_raw"].verdict.value == "fail"
    assert checks["host.nic.traffic"].found == "not checked: no CAP_NET_RAW"
    assert {checks[f"ethercat.{name}"].found for name in CHECKS} == {"not checked: no CAP_NET_RAW"}
