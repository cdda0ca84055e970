"""The learned model: the network, its checkpoint I/O without the trainer, the data evidence stored with it, versioned
checkpoints.
"""

__all__ = [
    "checkpoint",
    "evidence",
    "io",
    "network",
]
