"""Data in, ROS-free: the replay buffer, pairing of messages into transitions (exact stamps and resampled),
plausibility bounds, the several-publishers decision.
"""

__all__ = [
    "buffer",
    "pairing",
    "plausibility",
    "publishers",
    "resampling",
]
