"""Recordings of a run: ROS 2 messages in MCAP, written off the control thread; plots of a recording."""
