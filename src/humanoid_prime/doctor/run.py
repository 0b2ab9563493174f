"""One doctor run: every check of the backends asked for, host and robot always, into one report.

The order is chosen for time, not for the report (which prints host, EtherCAT, CAN, robot): the robot's files
first (they name the NIC and the rates), then the watch on the ring's NIC starts in the background, the latency
probe runs, the ring is scanned and read, the watch ends (a second has passed by then), and the wrists are heard.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from humanoid_prime.config.controllers import ControllersConfig
from humanoid_prime.config.location import ConfigFiles
from humanoid_prime.doctor import BACKENDS, host, latency
from humanoid_prime.doctor import can as can_checks
from humanoid_prime.doctor import ethercat as ethercat_checks
from humanoid_prime.doctor.report import Check, Report, not_run
from humanoid_prime.doctor.robot import robot_checks
from humanoid_prime.doctor.system import Json, System, ip_link, ip_links, nic_state
from humanoid_prime.runtime.session import default_bringup_rate

NIC_CHECKS = ("nic", "nic.up", "nic.carrier", "nic.speed", "cap_net_raw", "nic.addresses", "nic.users", "nic.traffic",
              "nic.irq")


@dataclass
class DoctorOptions:
    files: ConfigFiles
    backends: tuple[str, ...] = BACKENDS
    interface: str | None = None  # the ring's NIC, instead of buses.ethercat.interface
    interface_source: str = "--interface"  # what to call where that name came from
    can_interface: str | None = None
    can_channel: str | None = None
    rate: float | None = None  # --rate: a period to judge the latency against, and the ring's with --op
    op: bool = False
    last_run: Path | None = None
    last_run_summary: Json | None = None  # robot.read_summary of last_run
    folded_dir: Path | None = None
    root: Path = Path("/")
    watch_s: float = host.LISTEN_S
    probe_s: float = latency.PROBE_S
    listen_s: float = can_checks.LISTEN_S
    context: dict[str, object] = field(default_factory=dict)


class _Watch:
    """The ring's NIC watched in a thread for ``seconds`` (``host.watch``)."""

    def __init__(self, interface: str, seconds: float, after: Check) -> None:
        self.interface = interface
        self.after = after  # the report line its own goes after
        self.traffic: host.Traffic | None = None
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, args=(seconds,), name="prime-doctor-watch", daemon=True)
        self._thread.start()

    def _run(self, seconds: float) -> None:
        try:
            self.traffic = host.watch(self.interface, seconds)
        except OSError as exc:
            self.error = f"no raw socket on {self.interface}: {exc.strerror or exc}"

    def check(self) -> Check:
        self._thread.join()
        if self.traffic is None:
            return not_run(host.GROUP, "nic.traffic", self.error or "the watch ended without an answer")
        return host.traffic_check(self.interface, self.traffic)


def _nic(report: Report, system: System, capabilities: int | None, interface: str, key: str,
         watch_s: float) -> tuple[_Watch | None, bool]:
    """The checks of the ring's NIC; the watch on it where a raw socket may be opened, and whether the ring may be
    scanned (nothing else holds the NIC)."""
    nic = nic_state(interface, *ip_link(interface), system)
    nic_part = host.nic_checks(nic, key, ip_links())
    raw = host.raw_socket_check(capabilities, interface)
    report.add(*nic_part, raw)
    if nic.exists:
        users = host.sockets_check(interface, system.socket_holders(system.packet_sockets(nic.ifindex or -1)))
        report.add(host.addresses_check(interface, host.addresses(interface)), users,
                   host.irq_check(interface, system.interrupts_of(interface), system.isolated_cpus()))
    else:
        users = not_run(host.GROUP, "nic.users", f"no interface {interface!r}")
        report.add(not_run(host.GROUP, "nic.addresses", f"no interface {interface!r}"), users,
                   not_run(host.GROUP, "nic.irq", f"no interface {interface!r}"))
    usable = all(c.verdict.value != "fail" for c in nic_part)
    if not usable or raw.verdict.value != "pass":
        why = f"{interface} is not usable" if not usable else "no CAP_NET_RAW"
        report.checks.insert(report.checks.index(users) + 1, not_run(host.GROUP, "nic.traffic", why))
        report.add(*(not_run(ethercat_checks.GROUP, name, why) for name in ethercat_checks.CHECKS))
        return None, False
    if users.verdict.value == "fail":  # a master may be running the ring: a scan would take its slaves to INIT
        report.add(*(not_run(ethercat_checks.GROUP, name, f"another program has a raw socket on {interface} "
                                                          "(host nic.users); scanning beside a running master "
                                                          "would take its slaves to INIT")
                     for name in ethercat_checks.CHECKS))
        return _Watch(interface, watch_s, users), False
    return _Watch(interface, watch_s, users), True


def _timed(report: Report, stage: str, work: Callable[[], list[Check]]) -> list[Check]:
    began = time.monotonic()
    try:
        return work()
    finally:
        report.seconds[stage] = report.seconds.get(stage, 0.0) + time.monotonic() - began


def run_doctor(options: DoctorOptions) -> Report:
    report = Report(context=dict(options.context))
    files = options.files
    report.context["files"] = files.as_dict()
    system = System(options.root)
    began = time.monotonic()
    robot_part, loaded = robot_checks(files, last_run=options.last_run, summary=options.last_run_summary,
                                      folded_dir=options.folded_dir)
    report.seconds["robot"] = time.monotonic() - began
    report.add(*robot_part)
    hardware = loaded.robot.hardware if loaded.robot is not None else None
    capabilities, rights = host.host_rights(system)
    watch: _Watch | None = None
    scan = False
    interface = ""
    if "ec" in options.backends and hardware is None:
        report.add(*(not_run(host.GROUP, name, "the hardware file did not load") for name in NIC_CHECKS))
    elif "ec" in options.backends and hardware is not None:
        interface = options.interface or hardware.ethercat.interface
        key = options.interface_source if options.interface else f"buses.ethercat.interface in {hardware.path}"
        report.context["ethercat_interface"] = interface
        watch, scan = _nic(report, system, capabilities, interface, key, options.watch_s)
    report.add(*rights, *host.kernel_checks(system))
    periods = []
    if loaded.controllers is not None:
        periods.append((1.0 / loaded.controllers.update_rate,
                        f"update_rate {loaded.controllers.update_rate:g} Hz, {files.controllers.path.name}"))
    if options.rate is not None:
        periods.append((1.0 / options.rate, f"--rate {options.rate:g} Hz"))
    report.add(*_timed(report, "latency", lambda: [_latency(options, periods)]))
    if scan and hardware is not None:
        rates = _ring_rates(options.rate, loaded.controllers)
        report.add(*_timed(report, "ethercat", lambda: ethercat_checks.ethercat_checks(
            hardware, interface, rates=rates, op=options.op)))
    if watch is not None:
        traffic = _timed(report, "watch", lambda: [watch.check()])[0]
        report.checks.insert(report.checks.index(watch.after) + 1, traffic)
    if "can" in options.backends:
        if hardware is None:
            report.add(not_run(can_checks.GROUP, "link", "the hardware file did not load"))
        else:
            report.context["can"] = {"interface": options.can_interface or hardware.can.interface,
                                     "channel": options.can_channel or hardware.can.channel}
            report.add(*_timed(report, "can", lambda: can_checks.can_checks(
                hardware, interface=options.can_interface, channel=options.can_channel, op=options.op,
                seconds=options.listen_s)))
    return report


def _ring_rates(rate: float | None, controllers: ControllersConfig | None) -> tuple[float, float] | None:
    """(SYNC0 rate, bring-up loop rate) a bring-up takes the ring to OP at: ``--rate``, else the controllers file's
    update_rate, and the bring-up loop as a bring-up derives it; None where the controllers file did not load."""
    if controllers is None:
        return None
    update_rate = rate or controllers.update_rate
    return update_rate, default_bringup_rate(controllers.bringup_rate, update_rate)


def _latency(options: DoctorOptions, periods: list[tuple[float, str]]) -> Check:
    wakeups = latency.probe(options.probe_s, min([latency.PROBE_INTERVAL_S, *(p for p, _ in periods)]))
    if not periods:
        return not_run(latency.GROUP, "latency", f"no period to judge it against (the controllers file did not "
                                                 f"load and no --rate): {wakeups.as_dict()}")
    return latency.latency_check(wakeups, periods)
