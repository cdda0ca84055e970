"""Training engines: how :meth:`~saml_ros.core.training.PrimalDualTrainer.fit` runs epochs of Algorithm 1.

``base`` (the :class:`Engine` interface and the :class:`RunState` it works on), ``plain`` (autograd and
``torch.optim``, and the single online step), ``fast`` (the same algorithm hand-written: ``flat`` storage and
optimizers, ``closed_form`` spec-term gradients) and ``fused`` (the fast engine's steps in blocks in a C++ kernel,
``kernels/fused_step.cpp``; the fast engine's torch path where the kernel is off or not built). :data:`ENGINES` maps
``TrainConfig.engine`` to the class; a new engine is a new :class:`Engine` subclass and an entry here.
"""

from saml_ros.core.training.engines.base import Engine, RunState, minibatch_plan
from saml_ros.core.training.engines.fast import FastEngine
from saml_ros.core.training.engines.fused import FusedEngine
from saml_ros.core.training.engines.plain import PlainEngine, primal_dual_step

#: ``TrainConfig.engine`` -> engine class (names: :data:`saml_ros.core.training.config.ENGINE_NAMES`)
ENGINES: dict[str, type[Engine]] = {"fast": FusedEngine, "fast_torch": FastEngine, "plain": PlainEngine}

__all__ = ["ENGINES", "Engine", "FastEngine", "FusedEngine", "PlainEngine", "RunState", "minibatch_plan", "primal_dual_step"]
