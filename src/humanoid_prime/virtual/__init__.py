"""The virtual Prime: one MuJoCo plant for all 14 joints behind the real wire protocols, the eRob ring
on a veth pair and the Sito motors on a CAN bus, run as a separate process for hardware-in-the-loop."""
