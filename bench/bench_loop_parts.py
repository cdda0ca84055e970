"""Where a lockstep step's time goes, without ROS: ``./dev bench loop_parts [--mpc demo] [--steps 300] [--profile]``.

The MPC node's logic (:class:`~saml_ros.core.mpc.service.MPCService`) and the quadrotor simulator core answer each
other in one Python loop, as they do across processes in the lockstep loop, and each part of a step is timed:

* ``MPC control step`` (swap check, solve, clip, send, status values) and the ``solve`` inside it, with the SQP
  iterations per solve and the time per iteration;
* ``status values -> CDR`` (``mpc/status`` as the node writes it) and ``simulator step`` (validation,
  ``true_step``, ground contact, outputs);
* the message conversions of a step, object path (``to_msg`` + ``serialize_message``, ``deserialize_message``
  + ``from_msg``) against the CDR path the nodes use (:mod:`msg_schemas.cdr`).

``--mpc demo`` uses the demo's MPC settings (config/bringup_quadrotor.yaml: pad on the floor, tilt bound, guard;
f_hat, or the newest checkpoint of ``--checkpoints DIR``, e.g. a demo run's ``checkpoints``); ``plain`` the MPC
node's defaults. ``--profile`` adds cProfile's top functions of the loop. ``--save F`` keeps the loop's commands
and SQP iteration counts, ``--against F`` compares with them (exit status 1 unless identical): a speed change that
must not change what the MPC does is checked that way. The transport (DDS, executors) is
``bench closed_loop``'s; see docs/performance.md, "The loop".
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def _us(fn: Callable[[], Any], n: int = 3000) -> float:
    """Mean microseconds per call of ``fn`` over ``n`` calls (after one warm-up call)."""
    fn()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n * 1e6


def conversions() -> list[tuple[str, float, float]]:
    """(what, object path us, CDR path us) for the quadrotor's state and cmd."""
    from rclpy.serialization import deserialize_message, serialize_message

    from msg_schemas import RCLPY, get_schema
    from msg_schemas.cdr import CdrCodec

    q = get_schema("quadrotor")
    state, control = CdrCodec(q.state), CdrCodec(q.control)
    odom, joints = RCLPY.cls(q.state.msg_type), RCLPY.cls(q.control.msg_type)
    x = np.array([0.5, -0.3, 1.2, 0.1, 0.0, -0.2, 1.0, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0])
    u = np.full(4, 2.0)
    bs, bc = state.encode(x, 10**9), control.encode(u, 10**9)
    return [
        ("state: write", _us(lambda: serialize_message(q.state_to_msg(x, 10**9))), _us(lambda: state.encode(x, 10**9))),
        ("state: read", _us(lambda: q.state_from_msg(deserialize_message(bs, odom))), _us(lambda: state.decode(bs))),
        ("cmd: write", _us(lambda: serialize_message(q.control_to_msg(u, 10**9))), _us(lambda: control.encode(u, 10**9))),
        ("cmd: read", _us(lambda: q.control_from_msg(deserialize_message(bc, joints))), _us(lambda: control.decode(bc))),
    ]


def loop(mpc: str, steps: int, checkpoints: Path | None, profile: bool) -> dict[str, Any]:
    """Run ``steps`` lockstep steps in-process; per-part times (s) and iteration counts."""
    import torch

    from msg_schemas.cdr import NamedVectorCdr
    from msg_schemas.telemetry import mpc_status_values
    from saml_ros.bringup.config import default_config
    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.core.mpc.service import MPCService
    from saml_ros.core.systems import get_entry
    from saml_ros.core.worlds.sim_core import STATE
    from sim_nodes.binding import config_from_params
    from sim_nodes.quadrotor_sim import BINDING

    torch.set_num_threads(1)
    params = dict(default_config("quadrotor")["mpc"]) if mpc == "demo" else {"solver": "fast"}
    if checkpoints is not None:
        params["run_dir"] = str(checkpoints)

    class _Log:
        def info(self, text: str) -> None:
            pass

        def warning(self, text: str) -> None:
            pass

    sent: list[tuple[np.ndarray, int]] = []
    svc = MPCService(MPCConfig.from_params({"system": "quadrotor", **params}), lambda u, s: sent.append((u, s)),
                     _Log())
    svc.start()
    svc.stop()  # the checkpoint (if any) is loaded; no background polling during the measurement
    p = {spec.name: spec.default for spec in BINDING.param_table()}
    p.update(mode="lockstep", episode_steps=50, seed=0)
    entry = get_entry("quadrotor")
    core = entry.simulator(entry.make_system(), config_from_params(p), p)
    status = NamedVectorCdr()
    out = core.begin(time.monotonic_ns(), 10**9)
    parts: dict[str, list[float]] = {"step": [], "solve": [], "status": [], "sim": []}
    iters: list[float] = []
    prof = cProfile.Profile() if profile else None
    t_all = time.perf_counter()
    if prof is not None:
        prof.enable()
    for _ in range(steps):
        x, stamp = next((o[1], o[2]) for o in out if o[0] == STATE)
        assert x is not None
        t0 = time.perf_counter()
        _, values = svc.control_step(x, stamp, t0)
        t1 = time.perf_counter()
        status.encode(mpc_status_values(values), stamp)
        t2 = time.perf_counter()
        u, s = sent[-1]
        out = core.on_cmd(u, s, time.monotonic_ns())
        t3 = time.perf_counter()
        parts["step"].append(t1 - t0)
        parts["solve"].append(values["solve_time_ms"] * 1e-3)
        parts["status"].append(t2 - t1)
        parts["sim"].append(t3 - t2)
        iters.append(values["iterations"])
    if prof is not None:
        prof.disable()
    return {"wall": time.perf_counter() - t_all, "parts": parts, "iterations": np.array(iters), "prof": prof,
            "model_version": svc.model_version, "commands": np.array([u for u, _ in sent]),
            "kernel": svc.diagnostic_values().get("solver_kernel", "n/a")}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_loop_parts", description=(__doc__ or "").splitlines()[0])
    p.add_argument("--mpc", default="plain", choices=("plain", "demo"), help="the MPC's settings (see above)")
    p.add_argument("--checkpoints", type=Path, help="plan with the newest checkpoint of this directory")
    p.add_argument("--steps", type=int, default=300, help="lockstep steps (6 landing episodes of 50)")
    p.add_argument("--profile", action="store_true", help="also print cProfile's top 30 functions by cumulative time")
    p.add_argument("--save", type=Path, metavar="NPZ",
                   help="save the loop's commands and SQP iteration counts (to check a later change against)")
    p.add_argument("--against", type=Path, metavar="NPZ",
                   help="compare the commands and iteration counts with a --save file of the same settings: a "
                        "speed change that must not change what the MPC does shows 0 and 'identical'")
    p.add_argument("--no-conversions", action="store_true",
                   help="skip the message conversion timings (a few seconds; for --save / --against checks)")
    p.add_argument("--tol", type=float, default=0.0, metavar="N",
                   help="with --against: commands within N (newtons) and equal iteration counts count as 'equal "
                        "within N' (exit status 0); for a change of summation order, such as the SQP's C kernel "
                        "against its numpy path (SAML_MPC_NATIVE=0)")
    args = p.parse_args(argv)
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    if not args.tol >= 0.0:
        p.error(f"--tol must be >= 0, got {args.tol}")
    r = loop(args.mpc, args.steps, args.checkpoints, args.profile)
    print(f"lockstep loop in-process (no ROS), quadrotor, MPC {args.mpc} settings, model version "
          f"{r['model_version']}, SQP numerics {r['kernel']}: {args.steps} steps in {r['wall']:.2f} s = {args.steps * 0.1 / r['wall']:.1f}x real "
          f"time; load average {load}")
    names = {"step": "MPC control step", "solve": "  of which the solve", "status": "status values -> CDR",
             "sim": "simulator step"}
    for key, label in names.items():
        v = np.asarray(r["parts"][key]) * 1e3
        print(f"  {label:<22} median {np.median(v):7.3f} ms  mean {v.mean():7.3f} ms  p90 {np.percentile(v, 90):7.3f} ms")
    it = r["iterations"]
    per_iter = 1e3 * float(np.sum(r["parts"]["solve"])) / max(float(it.sum()), 1.0)
    print(f"  SQP iterations per solve: median {np.median(it):.0f}, mean {it.mean():.2f}, max {it.max():.0f}; "
          f"{per_iter:.3f} ms per iteration")
    if not args.no_conversions:
        print("message conversions per message (us): object path (to_msg + serialize / deserialize + from_msg) vs "
              "CDR")
        for what, obj, cdr in conversions():
            print(f"  {what:<14} {obj:7.1f} vs {cdr:6.1f}  ({obj / cdr:.1f}x)")
    if args.save is not None:
        np.savez(args.save, commands=r["commands"], iterations=it)
        print(f"  saved the commands and iteration counts to {args.save}")
    status = 0
    if args.against is not None:
        ref = np.load(args.against)
        same_shape = ref["commands"].shape == r["commands"].shape
        du = float(np.abs(ref["commands"] - r["commands"]).max()) if same_shape else float("inf")
        same_iters = same_shape and np.array_equal(ref["iterations"], it)
        verdict = "DIFFERENT"
        if same_iters and du == 0.0:
            verdict = "identical"
        elif same_iters and du <= args.tol:
            verdict = f"equal within {args.tol:g}"
        print(f"  against {args.against}: max |command difference| {du:.3g}, iteration counts "
              f"{'equal' if same_iters else 'differ'}: {verdict}")
        status = 0 if verdict != "DIFFERENT" else 1
    if r["prof"] is not None:
        pstats.Stats(r["prof"]).sort_stats("cumulative").print_stats(30)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
