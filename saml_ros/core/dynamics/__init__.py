"""The dynamics every layer builds on (no registry, no MPC, no simulator): the System contract, quaternion helpers, the
f_hat building blocks of system files.
"""

__all__ = [
    "base_forms",
    "base_models",
    "quaternion",
    "system",
]
