"""Trajectory evaluation: read, associate, align, and score estimates against ground truth.

Numbers agree with evo 1.38 (the reference tool) to 1e-9 relative; see ``tests/test_eval_*.py``.
Modules import only numpy at load time so that ``slam eval`` starts fast; matplotlib, scipy and
the ROS readers are imported inside the functions that need them.
"""
