"""Simulated Prime: MuJoCo plant and the demonstration run."""
