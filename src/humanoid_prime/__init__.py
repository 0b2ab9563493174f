"""Bringup and control stack for Prime, a 14-joint bimanual humanoid (eRob on EtherCAT, Sito on CAN)."""

__version__ = "0.1.0"
