"""The doctor: checks of the host, the buses and the robot before anything moves, each with its fix."""

BACKENDS = ("ec", "can")  # the buses it may check: EtherCAT, CAN
