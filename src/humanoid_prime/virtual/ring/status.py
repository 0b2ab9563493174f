"""What the emulator's control channel tells about one slave (``status``): its ESC, its distributed clock, its
mailbox faults, its drive and its joint, as plain JSON values for the tests and the tools that watch the ring."""

from __future__ import annotations

from typing import Any

from humanoid_prime.drivers.ethercat.wire import AL_STATE_NAMES
from humanoid_prime.virtual.ring.drive import Cia402State
from humanoid_prime.virtual.ring.ring import Ring


def describe_slave(ring: Ring, position: int, now: int) -> dict[str, Any]:
    """The slave at ring ``position`` as the control channel's ``status`` tells it (``now``: the server's clock, ns)."""
    slave = ring.slaves[position]
    esc = slave.esc
    drive = slave.drive
    kp, kd, ki = drive.gains
    return {
        "position": position,
        "powered": ring.powered[position],
        "reachable": slave in ring.reachable,
        "silent": slave.silent,
        "station_address": esc.station_address,
        "al_state": AL_STATE_NAMES[slave.state],
        "al_status": esc.al_status,
        "al_status_code": esc.al_status_code,
        "al_pending_op": slave.pending_op,
        "al_change_frames": list(slave.change_frames),
        "dc": {
            "activation": esc.clock.activation,
            "sync0_cycle_ns": esc.clock.sync0_cycle_ns,
            "sync0_running": esc.clock.sync0_running(now),
            "locked": slave.locked,
            "lock_count": slave.lock_count,
            "time_samples": esc.clock.samples,
            "time_difference_ns": esc.clock.difference_ns,
        },
        "mailbox_faults": slave.mailbox_faults,
        "drive": {
            "state": Cia402State(drive.state).name,
            "statusword": int(drive.statusword.value),
            "controlword": int(drive.controlword.value),
            "error_code": int(drive.error_code.value),
            "error_history": drive.error_history,
            "mode_display": int(drive.mode_display.value),
            "target_position": int(drive.target_position.value),
            "position_actual": int(drive.position_actual.value),
            "velocity_actual": int(drive.velocity_actual.value),
            "torque_actual": int(drive.torque_actual.value),
            "gate": int(drive.gate.value),
            "pos_reg": int(drive.pos_reg.value),
            "vel_reg": int(drive.vel_reg.value),
            "integral": int(drive.integral_reg.value),
            "kp": kp,
            "kd": kd,
            "ki": ki,
            "torque_nm": drive.torque_nm,
        },
        "joint": {
            "q_rad": float(ring.plant.q[position]),
            "qd_rad_s": float(ring.plant.qd[position]),
            "external_nm": float(ring.plant.external[position]),
        },
    }
