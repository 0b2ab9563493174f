"""A frame-level EtherCAT slave ring of emulated eRob drives that a real master (SOEM through pysoem)
drives as it would the robot; DESIGN §4.2. Run it with ``prime emulate ec`` or
``python -m humanoid_prime.virtual.ring``; tests use ``humanoid_prime.virtual.netns.EmulatedRing``.

What SOEM (as bundled with pysoem 1.1.13) sends, and which part answers:

- ``config_init``: BWR 0x0101/0x0120/..., BRD 0x0000 (the working counter is the slave count), per
  slave APRD 0x0140, APWR 0x0010 (station address 0x1001, 0x1002, ...), FPRD 0x0012, 0x0502; SII words
  0x08, 0x0E, 0x0A, 0x0C, 0x18, 0x1A, 0x1C through 0x0502-0x0508; FPRD 0x0008 (DC support), 0x0110
  (topology); SII categories General, Strings, SM and FMMU for the first slave of each identity (later
  ones are copied); FPWR SM0+SM1 in one datagram; FPWR 0x0120 = PRE-OP + ack. -> ``esc``, ``sii``.
- ``config_map``: per slave CoE uploads of 0x1C00:00, 0x1C00:03/04, 0x1C12/0x1C13 and the mapped
  0x1600/0x1A00 entries (no complete access unless the SII General category advertises it), then FPWR
  SM2/SM3 and one FMMU per direction, FPWR 0x0120 = SAFE-OP. Outputs of all slaves come first in the
  logical image, inputs after them; expected working counter = 2 * output slaves + input slaves.
  -> ``mailbox``, ``firmware``.
- ``config_dc``: BWR 0x0900 (latch receive times), per slave FPRD 0x0900, 0x0918, FPWR 0x0920 (offset
  so that system time = master time since 2000), FPRD 0x0904-0x090C, FPWR 0x0928 (propagation delay).
  ``dc_sync(True, cycle)``: FPWR 0x0981 = 0, 0x0980 = 0, FPRD 0x0910, FPWR 0x0990 = a whole multiple of
  the cycle at least 100 ms ahead, 0x09A0 = cycle, 0x0981 = 3. -> ``esc``.
- ``send_processdata``: one LRW over the image, followed in the same frame by FRMW 0x0910 (8 bytes) on
  the reference clock (first DC slave) once ``config_dc`` found DC. ``receive_processdata`` copies the
  whole LRW data back (so a slave must leave output bytes alone) and returns its working counter.
  -> ``ring``, ``firmware``.
- ``state_check``/``read_state``: BRD or FPRD of 0x0130 (6 bytes: status, reserved, status code).
- SDO: wait for SM0 status bit 3 clear, FPWR the whole write mailbox, poll SM1 status (FPRD 0x080D)
  until bit 3 is set, FPRD the whole read mailbox; SOEM's frame timeout is 2 ms (EC_TIMEOUTRET) and the
  SDO timeout 700 ms. -> ``esc``, ``mailbox``.
"""
