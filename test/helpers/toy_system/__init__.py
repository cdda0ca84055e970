"""A toy fourth system laid out like a built-in one (``saml_ros/systems/<name>/``), outside the package: a cart on
a line with quadratic drag the base model does not know.

``model.py`` (its ``System``), ``task.py`` (its shooting MPC problem), ``world.py`` (its stepped simulator world),
``schema.py`` (its topics; a built-in system keeps these in ``msg_schemas/``) and ``entry.py`` (its registry entry).
Adding it to saml_ros is this folder and one line, ``register_system(ENTRY)``
(test/unit/systems/test_toy_system.py); no numpy twin (the MPC differentiates the torch model).
"""

from helpers.toy_system.entry import ENTRY

__all__ = ["ENTRY"]
