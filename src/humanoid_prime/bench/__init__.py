"""Benchmarks behind ``make bench``: each module measures one DESIGN §6 target and returns its figures."""

# DESIGN §6, the one place these numbers live.
# MujocoSystem + controllers, headless, 50 Hz control and 1 kHz physics: this share of MuJoCo's own stepping speed of
# the same model in the same run (the host moves MuJoCo's own speed by half within minutes)
TARGET_FLOOR_FRACTION = 0.9
TARGET_BRINGUP_S = 1.5  # cold bring-up of 10 eRob to OP with joint states flowing
TARGET_SWITCH_S = 0.020  # a mode switch's gains on all 10 eRob (one 50 Hz tick)
TARGET_SKEW_S = 0.005  # between the slaves of one switch
TARGET_TICK_MEDIAN_US = 100.0  # read + update + write, 14 joints, our CPU (without bus I/O)
TARGET_TICK_P99_US = 300.0
TARGET_JITTER_P99_US = 500.0  # loop period at 50 Hz
TARGET_KHZ_OVERRUNS = 0  # 1 kHz for 60 s on the emulated robot, idle machine
TARGET_LOAD_PERCENT = 5.0  # Sito bus at 50 Hz
TARGET_DDS_ADDED_TICK_US = 30.0  # what --dds adds to the median tick
TARGET_RECORD_ADDED_TICK_US = 20.0  # what --record adds to the median tick
TARGET_GATE_ADDED_TICK_US = 50.0  # what the command gate's body check adds to the median tick at 50 Hz
TARGET_STARTUP_S = 0.3  # prime --help, info, switch, decode from the shell to their exit (median)
TARGET_DOCTOR_S = 10.0  # prime doctor on the healthy virtual Prime: start-up plus checks
