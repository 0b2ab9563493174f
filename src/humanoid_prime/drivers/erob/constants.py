"""eRob hardware constants (DESIGN §2). One place, so a re-measurement is a one-line change."""

import math

VENDOR_ID = 0x5A65726F
PRODUCT_CODE = 0x00029252

COUNTS_PER_REV = 524288  # 2**19 absolute multi-turn output encoder
COUNTS_PER_RAD = COUNTS_PER_REV / (2.0 * math.pi)

EROB80_KT_NM_PER_MA = 0.134e-3  # eRob80 V5_MC2
# Output torque that 0x6077 / 0x60B2 count in per-mille (0x6076, rated torque). Nominal eRob70 50:1 figure,
# not yet read off a Prime drive: read 0x6076 (and the gear) on one and correct this line if they differ.
RATED_TORQUE_NM = 23.0

MIN_CYCLE_S = 500e-6
MODE_CSP = 8
