"""The topics a recording can hold (``--topics`` chooses among them), apart from the recorder so the command
line can check the option without importing it."""

JOINT_STATES = "/prime/joint_states"
COMMAND = "/prime/command"  # the MIT command the controller manager wrote to the hardware
REMOTE = "/remote_policy_controller/command"
TOPICS = (JOINT_STATES, COMMAND, "/control_mode", "/safety_status", "/diagnostics", "/robot_description", "/tf",
          "/tf_static", "/clock", REMOTE)
