"""Experiment runners reproducing the paper's tables and figures (``./dev experiment NAME``).

One module per experiment: :mod:`.friction`, :mod:`.convergence`, :mod:`.paddle_ball`, :mod:`.quadrotor`; each
has a settings dataclass (paper defaults, ``quick()`` for a short run) and ``run(settings, out, progress)``
that writes ``results.md``, ``results.json`` and PNG figures into ``out`` and returns the results dict.
See docs/experiments.md.
"""

EXPERIMENT_NAMES: tuple[str, ...] = ("friction", "convergence", "paddle_ball", "quadrotor")
#: runners of the same form that ``experiment all`` does not run (longer, and no claim of the paper's table):
#: :mod:`.capacity`, the net-size sweep on the demo's landing
SWEEPS: tuple[str, ...] = ("capacity",)
