"""Runtime helpers of the nodes and the learner's processes: lifecycle, the training device, where native code is
built, starting the training interpreter.
"""

__all__ = [
    "child_launch",
    "device",
    "lifecycle",
    "native_build",
]
