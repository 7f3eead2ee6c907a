"""Reference benchmark harness for human motion priors.

Units inside the code: metres, seconds, radians. World frame: y up, facing +z,
left at +x. Skeleton: the SMPL 22-joint body (see :mod:`benchmark.core.skeleton`).
"""

__version__ = "0.1.0"
