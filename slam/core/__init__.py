"""The bottom of the imports: the types and helpers every other package shares.

messages (every object that crosses a thread or process boundary), calibration, geometry,
trajectory, errors, atomic file output, config bounds and latency summaries. Nothing here
imports anything else of the project outside ``slam.core``.
"""
