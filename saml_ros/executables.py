"""The saml_ros executables: the one table (name -> ``"module:function"``) and the dispatcher that runs them.

``setup.py`` turns :data:`EXECUTABLES` into console scripts (``ros2 run saml_ros <name>`` after a colcon build;
it reads this file with :mod:`ast`, so keep the table a plain dict literal), and :func:`main` runs any of them by
name: ``python -m saml_ros.executables NAME [args...]`` (what ``./dev NAME`` does). Every target function takes
no arguments, reads ``sys.argv`` and returns an exit code (or ``None`` for 0).

The target module is imported only when asked for, so ``./dev record`` never imports torch unless the
recorder does. ``sys.argv`` is rewritten to ``[NAME, args...]`` so argparse shows the executable's name,
exactly as the console script installed by colcon would.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

EXECUTABLES: dict[str, str] = {
    "learner": "saml_ros.nodes.learner:main",
    "mpc": "saml_ros.nodes.mpc:main",
    "friction_sim": "sim_nodes.friction_sim:main",
    "paddle_ball_sim": "sim_nodes.paddle_ball_sim:main",
    "quadrotor_sim": "sim_nodes.quadrotor_sim:main",
    "record": "saml_ros.bags.record:main",
    "play": "saml_ros.bags.play:main",
    "bringup": "saml_ros.bringup:main",
    "train": "saml_ros.offline.cli:main",
    "export": "saml_ros.offline.export_cli:main",
    "sweep": "saml_ros.offline.sweep_cli:main",
    "experiment": "saml_ros.experiments.cli:main",
    "bag_info": "saml_ros.bags.info:main",
    "demo": "saml_ros.demo:main",
    "layouts": "saml_ros.viewers.cli:main",
    "foxglove_server": "saml_ros.viewers.foxglove_server:main",
    "lifecycle_manager": "saml_ros.nodes.lifecycle_manager:main",
}

#: exit code for an unknown or unavailable executable (same as argparse's usage errors)
USAGE_ERROR = 2


def usage() -> str:
    """One line per executable: ``name  module:function``."""
    width = max(len(n) for n in EXECUTABLES)
    lines = [f"  {name:<{width}}  {target}" for name, target in EXECUTABLES.items()]
    return "usage: python -m saml_ros.executables NAME [args...]\nexecutables:\n" + "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int | str | None:
    """Dispatch to ``EXECUTABLES[argv[0]]`` with ``sys.argv = [name, *argv[1:]]``.

    Returns what the executable's function returns (an exit code, a message or ``None``), which
    ``sys.exit`` treats exactly as the installed console script does.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if args else sys.stderr)
        return 0 if args else USAGE_ERROR
    name, rest = args[0], args[1:]
    target = EXECUTABLES.get(name)
    if target is None:
        print(f"unknown executable {name!r}; valid names: {', '.join(EXECUTABLES)}", file=sys.stderr)
        return USAGE_ERROR
    module_name, func_name = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        # Only a missing *target* module is a usage problem; a missing dependency inside it is a bug
        # whose traceback the user needs.
        if exc.name is None or not (module_name == exc.name or module_name.startswith(exc.name + ".")):
            raise
        print(f"executable {name!r} is not available: module {module_name!r} not found", file=sys.stderr)
        return USAGE_ERROR
    func = getattr(module, func_name)
    sys.argv = [name, *rest]
    result: int | str | None = func()
    return result


if __name__ == "__main__":
    sys.exit(main())
