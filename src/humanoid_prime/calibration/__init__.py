"""Per-robot calibration: sweep math, direction flips, mirror check and the eRob fold."""
