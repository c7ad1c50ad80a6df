"""Sequence sources (MCAP, ROS 2 bags, EuRoC/TUM-VI folders) and the synthetic generator."""
