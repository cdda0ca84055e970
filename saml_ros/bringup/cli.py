"""``ros2 run saml_ros bringup``: start a whole closed loop (simulator, learner, MPC) as separate processes.

    bringup --system quadrotor --sim-time 60                 # lockstep, defaults of config/bringup_quadrotor.yaml
    bringup --config config/bringup_quadrotor.yaml --set mpc.solver=slsqp --set sim.episode_steps=60
    bringup --system friction --record runs/bag --domain-id 17
    bringup --system-file examples/diff_drive/system.yaml --robot "python examples/diff_drive/robot.py"

A robot described by a system file (docs/your_robot.md) runs with the learner and the MPC on its file, beside the
robot's own processes (``--robot CMD``, repeatable, each started in the robot's namespace ``/<name>`` after the
learner and the MPC are active; without it, the robot is already running); ``--sim-time`` then counts the seconds
of the robot's state stamps.

What it does:

1. makes a private run directory (``--run-dir``, default ``runs/bringup-<system>-<date>-<pid>``) holding the
   learner's checkpoints, one ROS parameter file per node (``params/<node>.yaml``) and each child's log
   (``logs/<node>.log``);
2. starts the learner and the MPC (and ``record`` with ``--record DIR``) in the system namespace
   ``/<system>``, each in its own process group and unconfigured (``autostart: false``), configures and then
   activates both through their lifecycle services (``lifecycle_msgs/srv/ChangeState``; a failed transition
   stops the run, the node's log says why), waits until they subscribe to ``state``, then starts the
   simulator (lockstep by default, so the loop runs as fast as its slowest participant);
3. prints a progress line every ``--progress-period`` wall seconds, read from the topics (simulated time from
   the state stamps, episodes, the learner's in-region model error, the MPC's model version and solve time);
4. stops after ``--sim-time`` seconds of simulated time (passed as the simulator's ``max_sim_time``: it ends
   the run itself at the first state at or after that time, so nothing beyond it is simulated or recorded),
   on Ctrl-C (SIGINT) or SIGTERM: SIGINT to every child's process group, then SIGTERM, then SIGKILL for what
   is left (no orphans: children also get SIGTERM from the kernel if bringup itself dies, via
   ``PR_SET_PDEATHSIG``), and prints a before/after summary (model error, task error of the episodes flown on the base model vs the last ones).

Environment: ``ROS_DOMAIN_ID`` is respected (``--domain-id`` overrides it for this run);
``ROS_AUTOMATIC_DISCOVERY_RANGE`` defaults to ``LOCALHOST`` when unset. Children inherit both.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import yaml

from saml_ros.bringup.closed_loop import RunOptions, run
from saml_ros.bringup.config import apply_sets, load_config
from saml_ros.bringup.results import format_summary
from saml_ros.core.systems import system_names

#: the help text: this module's docstring
USAGE: str = __doc__ or ""


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``bringup`` (its help is this module's docstring)."""
    p = argparse.ArgumentParser(prog="bringup", description=USAGE.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=USAGE.split("\n", 1)[1])
    p.add_argument("--system", choices=system_names(), help="system to run (default: the config's, else quadrotor)")
    p.add_argument("--system-file", type=Path, help="a robot described by a system file with an mpc: section "
                                                    "(instead of --system / --config)")
    p.add_argument("--robot", action="append", default=[], metavar="CMD",
                   help="with --system-file: a command starting one of the robot's own processes (repeatable)")
    p.add_argument("--config", type=Path, help="bringup YAML (sections sim, learner, mpc; see config/bringup_quadrotor.yaml)")
    p.add_argument("--sim-time", type=float, help="stop after this many seconds of simulated time (0 = until Ctrl-C)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.PARAM=VALUE",
                   help="override a node parameter, e.g. --set mpc.solver=slsqp (repeatable)")
    p.add_argument("--run-dir", type=Path, help="run directory (default: a new runs/bringup-<system>-<date>-<pid>)")
    p.add_argument("--record", type=Path, help="also record the loop into this bag directory (saml_ros record)")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID for this run (default: the environment's)")
    p.add_argument("--no-learner", action="store_true", help="run simulator + MPC only (base model or run-dir checkpoints)")
    p.add_argument("--progress-period", type=float, default=5.0, help="seconds (wall) between progress lines")
    p.add_argument("--startup-timeout", type=float, default=90.0, help="seconds to wait for the nodes to come up")
    p.add_argument("--quiet", action="store_true", help="print only the summary")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """``bringup [options]``: run one closed loop, print the summary; exit 0 if it ran cleanly, 1 if not, 2 for
    bad options."""
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    if args.system_file is not None and (args.system or args.config):
        print("bringup: give --system-file, or --system / --config, not both", file=sys.stderr)
        return 2
    if args.robot and args.system_file is None:
        print("bringup: --robot needs --system-file", file=sys.stderr)
        return 2
    try:
        if args.system_file is not None:
            from saml_ros.bringup.config import robot_config

            config = apply_sets(robot_config(args.system_file, args.robot), args.set)
        else:
            config = apply_sets(load_config(args.config, args.system), args.set)
        if args.sim_time is not None:
            config["sim_time"] = args.sim_time
    except (OSError, ValueError, yaml.YAMLError) as exc:
        print(f"bringup: {exc}", file=sys.stderr)
        return 2
    if args.domain_id is not None and not 0 <= args.domain_id <= 101:
        print("bringup: --domain-id must be in 0..101", file=sys.stderr)
        return 2
    opts = RunOptions(run_dir=args.run_dir, record=args.record, domain_id=args.domain_id,
                      progress_period=args.progress_period, startup_timeout=args.startup_timeout,
                      quiet=args.quiet, learner=not args.no_learner)
    res = run(config, opts)
    print(format_summary(res), flush=True)
    return 0 if res.ok else 1
