"""MuJoCo: the model built from the robot description, and ``MujocoSystem``, the simulated Prime."""
