"""Benchmarks behind ``make bench``: each module measures one DESIGN §6 target and returns its figures."""

# DESIGN §6, the one place these numbers live.
TARGET_REALTIME_FACTOR = 20.0  # MujocoSystem + controllers, headless
TARGET_BRINGUP_S = 5.0  # cold bring-up of 10 eRob to OP with joint states flowing
TARGET_SWITCH_S = 0.1  # a mode switch's gains on all 10 eRob
TARGET_SKEW_S = 0.020  # between the slaves of one switch
TARGET_TICK_MEDIAN_US = 100.0  # read + update + write, 14 joints
TARGET_TICK_P99_US = 300.0
TARGET_JITTER_P99_US = 500.0  # loop period at 50 Hz
TARGET_LOAD_PERCENT = 5.0  # Sito bus at 50 Hz
TARGET_DDS_ADDED_TICK_US = 30.0  # what --dds adds to the median tick
TARGET_RECORD_ADDED_TICK_US = 20.0  # what --record adds to the median tick
