"""Physical floors the benchmark figures are shown beside: what the wire or the physics engine alone costs, so
the distance from each figure to its limit is visible.

- One EtherCAT cycle: the frame SOEM sends (one LRW datagram over every slave's outputs and inputs, one FRMW
  of the DC reference time) on the wire at 100 Mbit/s, plus the pass-through delay of each slave.
- The Sito frames of one bus cycle on CAN at 1 Mbit/s (a command, 0xB1 and 0xB2 per wrist): 29-bit
  identifier, 8 data bytes, without and with the worst-case stuff bits.
"""

from __future__ import annotations

from humanoid_prime.drivers.sito.bus import can_frame_bits

ETHERNET_OVERHEAD_BYTES = 8 + 14 + 4 + 12  # preamble and SFD, header, FCS, inter-frame gap
ETHERCAT_HEADER_BYTES = 2
DATAGRAM_OVERHEAD_BYTES = 10 + 2  # datagram header, working counter
DC_DATAGRAM_BYTES = DATAGRAM_OVERHEAD_BYTES + 8  # FRMW of the 64-bit system time
MIN_ETHERNET_PAYLOAD = 46
SLAVE_DELAY_S = 0.7e-6  # an ESC's forwarding delay in processing plus return (ET1100 datasheet class figure)


def ethercat_cycle_s(slaves: int, output_bytes: int, input_bytes: int, *, bit_rate: float = 100e6) -> float:
    """Wire time of one process-data cycle: the frame's bits at ``bit_rate`` plus every slave's delay."""
    payload = ETHERCAT_HEADER_BYTES + DATAGRAM_OVERHEAD_BYTES + slaves * (output_bytes + input_bytes) \
        + DC_DATAGRAM_BYTES
    frame = max(payload, MIN_ETHERNET_PAYLOAD) + ETHERNET_OVERHEAD_BYTES
    return frame * 8 / bit_rate + slaves * SLAVE_DELAY_S


def can_frame_s(data_bytes: int = 8, *, bit_rate: float = 1e6, worst_stuffing: bool = False) -> float:
    """Bus time of one extended CAN frame; with ``worst_stuffing`` one stuff bit per four stuffable bits."""
    return can_frame_bits(data_bytes, worst_stuffing=worst_stuffing) / bit_rate
