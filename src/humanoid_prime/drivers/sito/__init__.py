"""Sito TA40-50 wrist motors: native MIT over CAN."""
