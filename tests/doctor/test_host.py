"""The host's checks against a fake /sys and /proc tree: the real-time kernel, the governor, isolated CPUs and the
NIC's interrupts, the rights and limits of the process, the NIC's state and its other users."""

from __future__ import annotations

from collections import Counter

import pytest

from doubles.kernel import ALL_CAPS, link, nic_files, process, write_tree
from doubles.sockets import frame_elsewhere_at_each_bind
from humanoid_prime.doctor import host
from humanoid_prime.doctor.report import Verdict
from humanoid_prime.doctor.system import CAP_IPC_LOCK, CAP_NET_RAW, CAP_SYS_NICE, nic_state, parse_cpu_list
from humanoid_prime.virtual.netns import EmulatedRing, netns_unavailable_reason

RT_VERSION = "#1 SMP PREEMPT_RT Debian 6.1.90-1 (2024-05-03)\n"


def test_a_preempt_rt_kernel_passes_by_its_flag_or_its_version(tmp_path):
    flagged = write_tree(tmp_path / "a", {"sys/kernel/realtime": "1\n", "proc/sys/kernel/version": "#1 SMP\n"})
    named = write_tree(tmp_path / "b", {"proc/sys/kernel/version": RT_VERSION})
    assert host.kernel_check(flagged.realtime_flag(), flagged.kernel_version()).verdict is Verdict.PASS
    assert host.kernel_check(named.realtime_flag(), named.kernel_version()).verdict is Verdict.PASS


def test_a_kernel_without_preempt_rt_warns_with_the_kernel_to_install(tmp_path):
    system = write_tree(tmp_path, {"proc/sys/kernel/version": "#1 SMP PREEMPT_DYNAMIC Debian 6.1.90-1\n"})
    check = host.kernel_check(system.realtime_flag(), system.kernel_version())
    assert check.verdict is Verdict.WARN
    assert "PREEMPT_DYNAMIC" in check.found and "linux-image-rt-amd64" in check.fix


def test_a_powersave_governor_warns_naming_its_cpus_and_the_command(tmp_path):
    cpu = "sys/devices/system/cpu/cpu{}/cpufreq/scaling_governor"
    system = write_tree(tmp_path, {cpu.format(0): "performance\n", cpu.format(1): "powersave\n",
                                   cpu.format(2): "powersave\n", cpu.format(3): "schedutil\n"})
    check = host.governor_check(system.governors())
    assert check.verdict is Verdict.WARN
    assert check.found.startswith("powersave on CPUs 1-2; schedutil on CPUs 3")
    assert check.fix == "sudo cpupower frequency-set -g performance (Debian: linux-cpupower)"


def test_performance_everywhere_or_no_cpufreq_passes(tmp_path):
    cpu = "sys/devices/system/cpu/cpu{}/cpufreq/scaling_governor"
    system = write_tree(tmp_path / "a", {cpu.format(0): "performance\n", cpu.format(1): "performance\n"})
    assert host.governor_check(system.governors()).verdict is Verdict.PASS
    assert host.governor_check(write_tree(tmp_path / "b", {}).governors()).verdict is Verdict.PASS


def test_no_isolated_cpu_warns_with_the_boot_parameters(tmp_path):
    system = write_tree(tmp_path, {"sys/devices/system/cpu/isolated": "\n"})
    check = host.isolation_check(system.isolated_cpus())
    assert check.verdict is Verdict.WARN and "isolcpus=N nohz_full=N rcu_nocbs=N" in check.fix


def test_the_nic_interrupts_on_the_isolated_cpu_warn_with_the_affinity_to_write(tmp_path):
    system = write_tree(tmp_path, {
        "sys/devices/system/cpu/isolated": "3\n",
        "proc/interrupts": "           CPU0       CPU1       CPU2       CPU3\n"
                           "  44:          0          0          0          0  PCI-MSI 524288-edge  enp3s0\n"
                           "  45:       1200          0          0      98765  PCI-MSI 524289-edge  enp3s0-TxRx-0\n"
                           "  46:         10          0          0          0  PCI-MSI 524290-edge  enp3s1-TxRx-0\n",
        "proc/irq/44/smp_affinity_list": "0-2\n", "proc/irq/45/smp_affinity_list": "0-3\n",
        "proc/irq/46/smp_affinity_list": "3\n"})
    irqs = system.interrupts_of("enp3s0")
    assert irqs == {44: {0, 1, 2}, 45: {0, 1, 2, 3}}  # not enp3s1's
    check = host.irq_check("enp3s0", irqs, system.isolated_cpus())
    assert check.verdict is Verdict.WARN
    assert "isolated CPUs 3" in check.found
    assert check.fix.startswith("echo 0-2 | sudo tee /proc/irq/45/smp_affinity_list")


def test_the_nic_interrupts_off_the_isolated_cpu_pass(tmp_path):
    system = write_tree(tmp_path, {"sys/devices/system/cpu/isolated": "3\n",
                                   "proc/interrupts": "   CPU0\n  45:  1  PCI-MSI  enp3s0-TxRx-0\n",
                                   "proc/irq/45/smp_affinity_list": "0-2\n"})
    assert host.irq_check("enp3s0", system.interrupts_of("enp3s0"), system.isolated_cpus()).verdict is Verdict.PASS


def test_a_nic_with_no_interrupt_line_is_not_checked_and_says_why(tmp_path):
    system = write_tree(tmp_path, {"proc/interrupts": "   CPU0\n  45:  1  PCI-MSI  eth1\n"})
    check = host.irq_check("ecm0", system.interrupts_of("ecm0"), set())
    assert not check.ran and "names no interrupt after ecm0" in check.found


def test_no_cap_net_raw_fails_naming_the_interface_and_the_setcap_command(tmp_path):
    system = write_tree(tmp_path, process(ALL_CAPS & ~(1 << CAP_NET_RAW), uid=0))
    check = host.raw_socket_check(system.capabilities(), "enp3s0")
    assert check.verdict is Verdict.FAIL
    assert check.found == "no CAP_NET_RAW: SOEM cannot open a raw socket on enp3s0"
    assert check.fix.startswith("run as root, or grant it once: sudo setcap cap_net_raw")
    assert host.raw_socket_check(write_tree(tmp_path / "b", process(1 << CAP_NET_RAW)).capabilities(),
                                 "enp3s0").verdict is Verdict.PASS


def test_real_time_priority_comes_from_cap_sys_nice_or_the_rtprio_limit(tmp_path):
    nice = write_tree(tmp_path / "a", process(1 << CAP_SYS_NICE))
    limited = write_tree(tmp_path / "b", process(0, rtprio="95"))
    low = write_tree(tmp_path / "c", process(0, rtprio="20"))
    for system, verdict in ((nice, Verdict.PASS), (limited, Verdict.PASS), (low, Verdict.FAIL)):
        assert host.rtprio_check(system.capabilities(), system.limit("Max realtime priority")).verdict is verdict
    failing = host.rtprio_check(low.capabilities(), low.limit("Max realtime priority"))
    assert "ulimit -r is 20" in failing.found and "/etc/security/limits.d/99-prime.conf" in failing.fix


def test_locked_memory_needs_cap_ipc_lock_or_no_limit(tmp_path):
    locked = write_tree(tmp_path / "a", process(1 << CAP_IPC_LOCK))
    unlimited = write_tree(tmp_path / "b", process(0, memlock="unlimited"))
    small = write_tree(tmp_path / "c", process(0, memlock="8388608"))
    for system, verdict in ((locked, Verdict.PASS), (unlimited, Verdict.PASS), (small, Verdict.FAIL)):
        assert host.memlock_check(system.capabilities(), system.limit("Max locked memory")).verdict is verdict
    assert "8192 KiB" in host.memlock_check(small.capabilities(), small.limit("Max locked memory")).found


def test_a_nic_that_is_missing_fails_and_lists_the_ones_there(tmp_path):
    checks = host.nic_checks(nic_state("enp9s0", False, None, write_tree(tmp_path, {})), "buses.ethercat.interface",
                             ["lo", "enp3s0", "wlan0"])
    assert [(c.name, c.verdict, c.ran) for c in checks] == [
        ("nic", Verdict.FAIL, True), ("nic.up", Verdict.WARN, False), ("nic.carrier", Verdict.WARN, False),
        ("nic.speed", Verdict.WARN, False)]
    assert "this machine has: enp3s0, wlan0" in checks[0].found


def test_a_nic_that_is_down_fails_with_the_command_that_brings_it_up(tmp_path):
    system = write_tree(tmp_path, nic_files("enp3s0"))
    checks = host.nic_checks(nic_state("enp3s0", True, link("enp3s0", ["BROADCAST", "MULTICAST"], operstate="DOWN"),
                                       system), "key", [])
    assert checks[1].verdict is Verdict.FAIL and checks[1].fix == "sudo ip link set enp3s0 up"


def test_no_carrier_fails_and_leaves_the_speed_unchecked(tmp_path):
    system = write_tree(tmp_path, nic_files("enp3s0", speed="-1\n"))
    nic = nic_state("enp3s0", True, link("enp3s0", ["NO-CARRIER", "BROADCAST", "UP"], operstate="DOWN"), system)
    checks = {c.name: c for c in host.nic_checks(nic, "key", [])}
    assert checks["nic.carrier"].verdict is Verdict.FAIL
    assert "first drive's IN port" in checks["nic.carrier"].fix
    assert not checks["nic.speed"].ran


def test_the_link_speed_is_judged_against_ethercat_s_100_mbit(tmp_path):
    def speed(value: str, duplex: str = "full\n") -> Verdict:
        system = write_tree(tmp_path / value.strip() / duplex.strip(), nic_files("enp3s0", speed=value,
                                                                                 duplex=duplex))
        return host.speed_check(nic_state("enp3s0", True, link("enp3s0", ["UP", "LOWER_UP"]), system)).verdict

    assert speed("100\n") is Verdict.PASS
    assert speed("1000\n") is Verdict.WARN  # something other than an ESC on the cable
    assert speed("10\n") is Verdict.FAIL
    assert speed("100\n", "half\n") is Verdict.FAIL


def test_a_link_speed_in_another_namespace_s_sysfs_is_not_believed(tmp_path):
    system = write_tree(tmp_path, nic_files("ecm0", ifindex=7, speed="10000\n"))
    nic = nic_state("ecm0", True, link("ecm0", ["UP", "LOWER_UP"], ifindex=12), system)
    assert nic.speed_mbps is None and nic.carrier is True


def test_another_process_with_a_raw_socket_on_the_nic_fails_naming_it(tmp_path):
    system = write_tree(tmp_path, {
        "proc/net/packet": "sk       RefCnt Type Proto  Iface R Rmem   User   Inode\n"
                           "0000000000000000 3 3 0003 3 1 0 0 424242\n"
                           "0000000000000000 3 3 0003 5 1 0 0 515151\n",
        "proc/4321/comm": "ethercat_master\n", "proc/4321/fd/7": "->socket:[424242]",
        "proc/555/comm": "tcpdump\n", "proc/555/fd/3": "->socket:[515151]"})
    holders = system.socket_holders(system.packet_sockets(3))
    assert holders == {"socket:[424242]": {(4321, "ethercat_master")}}  # not tcpdump's, on interface 5
    check = host.sockets_check("enp3s0", holders, own_pid=1)
    assert check.verdict is Verdict.FAIL
    assert check.found.startswith("pid 4321 (ethercat_master): a raw socket on enp3s0")
    assert check.fix.startswith("stop it (kill 4321)")
    assert host.sockets_check("enp3s0", holders, own_pid=4321).verdict is Verdict.PASS  # the doctor's own


def test_a_raw_socket_no_process_holds_is_the_kernel_s_and_fails_too(tmp_path):
    system = write_tree(tmp_path, {"proc/net/packet": "sk RefCnt Type Proto Iface R Rmem User Inode\n"
                                                      "0000000000000000 3 3 0003 3 1 0 0 777\n"})
    check = host.sockets_check("enp3s0", system.socket_holders(system.packet_sockets(3)), own_pid=1)
    assert check.verdict is Verdict.FAIL and "an IgH master's generic driver?" in check.found


def test_addresses_on_the_ring_s_nic_warn_with_how_to_take_them_off():
    check = host.addresses_check("enp3s0", ["fe80::1/64"])
    assert check.verdict is Verdict.WARN
    assert "ip addr flush dev enp3s0" in check.fix and "nmcli device set enp3s0 managed no" in check.fix
    assert host.addresses_check("enp3s0", []).verdict is Verdict.PASS


def test_frames_the_host_sends_on_the_ring_s_nic_fail_with_how_to_keep_the_network_stack_off():
    traffic = host.Traffic(1.0, Counter({("sent", 0x86DD): 3, ("received", 0x0806): 1}), ethercat=40)
    check = host.traffic_check("enp3s0", traffic)
    assert check.verdict is Verdict.FAIL
    assert "1 ARP received, 3 IPv6 sent" in check.found
    assert check.fix.startswith("keep this host's network stack off enp3s0: nmcli device set enp3s0 managed no")
    assert host.traffic_check("enp3s0", host.Traffic(1.0, ethercat=40)).verdict is Verdict.PASS


def test_cpu_lists_read_as_the_kernel_writes_them():
    assert parse_cpu_list("0-2,5,7-8\n") == {0, 1, 2, 5, 7, 8}
    assert parse_cpu_list("") == set()


@pytest.mark.netns
@pytest.mark.skipif(netns_unavailable_reason() is not None, reason=f"no emulated ring: {netns_unavailable_reason()}")
def test_the_traffic_watch_counts_only_its_own_nics_frames_even_while_it_is_being_opened():
    """A frame another NIC sends while the watch's socket is not yet bound to its NIC is not this NIC's traffic."""
    ipv6 = bytes(12) + b"\x86\xdd" + bytes(46)
    with EmulatedRing(slaves=1) as ring, frame_elsewhere_at_each_bind(ipv6):  # (the ring is up before it)
        traffic = host.watch(ring.master_interface, seconds=0.05)
    assert traffic.frames == Counter()
