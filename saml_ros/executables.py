"""The saml_ros executables: the one table (name -> ``"module:function"``) and the dispatcher that runs them.

``setup.py`` turns :data:`EXECUTABLES` into console scripts (``ros2 run saml_ros <name>`` after a colcon build;
it reads this file with :mod:`ast`, so keep the table a plain dict literal), each calling :func:`entry`, which
dispatches on the script's name; :func:`main` runs any of them by name: ``python -m saml_ros.executables NAME [args...]`` (what ``./dev NAME`` does). Every target function takes
no arguments, reads ``sys.argv`` and returns an exit code (or ``None`` for 0).

The target module is imported only when asked for, so ``./dev record`` never imports torch unless the
recorder does. ``sys.argv`` is rewritten to ``[NAME, args...]`` so argparse shows the executable's name,
exactly as the console script installed by colcon would.
"""

from __future__ import annotations

import importlib
import os
import signal
import sys
from collections.abc import Callable, Sequence

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


def main(argv: Sequence[str] | None = None, before_run: Callable[[], None] | None = None) -> int | str | None:
    """Dispatch to ``EXECUTABLES[argv[0]]`` with ``sys.argv = [name, *argv[1:]]``; ``before_run`` is called once
    the target is imported, just before it runs.

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
    if before_run is not None:
        before_run()
    result: int | str | None = func()
    return result


def _quiet_stop_while_starting() -> None:
    """Until the executable's function runs, SIGINT / SIGTERM end the process at once with status 0: a node
    stopped while it still imports (torch takes seconds on a loaded machine) has nothing to save, and must not
    print a ``KeyboardInterrupt`` traceback or outlast ``ros2 launch``'s grace period. The nodes install their own
    handlers in their ``main``; :func:`_restore_default_signals` undoes these for everything else."""
    def stop(signum: int, frame: object) -> None:
        os._exit(0)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, stop)


def _restore_default_signals() -> None:
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def entry() -> int | str | None:
    """The console-script target of every executable (``lib/saml_ros/<name>``): runs the executable the script is
    named after (``sys.argv[0]``'s file name) through :func:`main`, quiet on a stop signal while it starts."""
    _quiet_stop_while_starting()
    return main([os.path.basename(sys.argv[0]), *sys.argv[1:]], _restore_default_signals)


if __name__ == "__main__":
    _quiet_stop_while_starting()
    sys.exit(main(None, _restore_default_signals))
