"""The learner node in real processes over real rclpy / Fast DDS (private ROS_DOMAIN_ID per learner).

The test process feeds the learner with stock rclpy publishers (messages built by msg_schemas from the
friction system's true dynamics), so it controls exactly what is sent: exact pairing across interleavings and
two namespaces, learning in the constrained region, decoding model_error with nothing but sensor_msgs, bad
input of each kind, configuration errors, resuming past a corrupt checkpoint, SIGKILL while checkpointing and
restart, SIGTERM with a final checkpoint.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from helpers import ros_helpers
from helpers.learner_node import BASE_PARAMS, DT_NS, SYSTEM, Learner, RosSide, episodes

#: processes this file SIGKILLs use UDP only, so they leave no Fast DDS shared-memory segments in /dev/shm
NO_SHM = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}


# ----------------------------------------------------------------------------------------------- helpers


# ---------------------------------------------------------------------------- the shared learner
SHARED_NS = ["/friction", "/exact_a", "/exact_b", "/nan_ns", "/shape_ns", "/order_ns", "/absurd_ns", "/wild_ns"]


@pytest.fixture(scope="module")
def shared(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Learner, RosSide, Path]]:
    """One learner with several namespaces (each test feeds its own, so counters are independent)."""
    tmp = tmp_path_factory.mktemp("shared")
    with ros_helpers.ros_domain("learner_shared") as dom:
        params = dict(BASE_PARAMS, namespaces=SHARED_NS, min_transitions=400, run_dir=str(tmp / "run"))
        learner = Learner(dom, params)
        tester = RosSide(dom.domain_id)
        try:
            learner.wait_log("training starts after")
            yield learner, tester, tmp
        finally:
            tester.close()
            print(f"--- shared learner log ---\n{learner.log()[-4000:]}")


def test_transitions_are_paired_exactly_per_namespace(shared: tuple[Learner, RosSide, Path]) -> None:
    """Two namespaces feeding one learner, interleaved with each other and within each (commands before their
    state, after the next state): the paired count of each equals what was sent."""
    _, tester, _ = shared
    rng = np.random.default_rng(1)
    a = episodes(150, rng, t0=10**9)
    b = episodes(120, rng, t0=10**9)  # the same stamps in another namespace: paired separately
    for ns in ("/exact_a", "/exact_b"):
        tester.connect(ns)
    i = j = 0
    while i < len(a) or j < len(b):  # interleave the namespaces in random chunks
        if j >= len(b) or (i < len(a) and rng.random() < 0.5):
            tester.send("/exact_a", a[i : i + 7])
            i += 7
        else:
            tester.send("/exact_b", b[j : j + 5])
            j += 5
    for ns, n in (("/exact_a", 150), ("/exact_b", 120)):
        tester.wait_received(ns)
        tester.wait(lambda ns=ns, n=n: tester.counter(f"{ns}/paired") == n, 5.0,  # type: ignore[misc]
                    f"{ns}/paired == {n}")
    for ns in ("/exact_a", "/exact_b"):
        for reason in ("duplicate", "out_of_order", "late", "unpaired", "nan", "shape"):
            assert tester.counter(f"{ns}/rejected/{reason}") == 0
    time.sleep(0.3)  # nothing more appears later
    assert tester.counter("/exact_a/paired") == 150 and tester.counter("/exact_b/paired") == 120


def test_model_error_in_the_constrained_region_falls(shared: tuple[Learner, RosSide, Path]) -> None:
    _, tester, _ = shared
    tester.connect("/friction")
    rng = np.random.default_rng(2)
    tester.send("/friction", episodes(1000, rng, t0=10**9, ep_len=3))
    tester.wait_received("/friction")

    with tester.lock:  # the untrained model (training starts at min_transitions = 400) on >= 200 transitions
        first = next(m for m in tester.telemetry if m["n_in/near_origin"] > 0 and m["window"] >= 200)
    assert first["updates"] == 0.0
    e0 = first["error_in/near_origin"]
    assert e0 > 0.07  # the base model misses the sticky friction patch near the origin (eps = 0.035)
    tester.wait(lambda: tester.last().get("error_in/near_origin", 1.0) < 0.5 * e0, 30.0,
                f"the in-region error to halve from {e0:.4f}")
    last = tester.last()
    assert last["updates"] > 0 and last["training"] == 1.0
    # the multiplier priced the constraint while it was violated; once it is met the default method (the
    # Lagrangian, Adam on lambda) may have brought lambda back to 0 by now (the kernel-fast learner: ~19,000 updates here)
    with tester.lock:
        assert max(m.get("lambda/near_origin", 0.0) for m in tester.telemetry) > 0
    assert np.isfinite(last["objective"]) and np.isfinite(last["lagrangian"])
    # training on the kernel can halve it before the stream's last transitions reach the buffer
    tester.wait(lambda: tester.last().get("buffer_size", 0) >= 1000, 5.0, "all 1000 transitions in the buffer")
    # /diagnostics counters can be one diagnostics period behind the pairing itself
    tester.wait(lambda: tester.counter("/friction/paired") == 1000, 5.0, "/friction/paired == 1000")
    time.sleep(0.3)
    assert tester.counter("/friction/paired") == 1000


STOCK_SUBSCRIBER = textwrap.dedent(
    """
    import json, sys, time
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    rclpy.init()
    node = rclpy.create_node("stock_listener")
    got = []
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(JointState, "/friction/learner/model_error", got.append, qos)
    deadline = time.monotonic() + 20
    while not got and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    assert got, "no learner/model_error message"
    msg = got[-1]
    values = dict(zip(msg.name, msg.position))
    foreign = sorted(m for m in sys.modules if m.split(".")[0] in ("saml_ros", "msg_schemas"))
    print(json.dumps({"values": values, "stamp": [msg.header.stamp.sec, msg.header.stamp.nanosec],
                      "velocity": len(msg.velocity), "effort": len(msg.effort), "foreign": foreign}))
    """
)


def test_stock_subscriber_decodes_model_error_from_the_message_type_alone(
    shared: tuple[Learner, RosSide, Path],
) -> None:
    learner, _, tmp = shared
    env = dict(os.environ, ROS_DOMAIN_ID=str(learner.domain), PYTHONPATH="")
    out = subprocess.run([sys.executable, "-c", STOCK_SUBSCRIBER], env=env, cwd=tmp, capture_output=True,
                         text=True, timeout=40)
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout.strip().splitlines()[-1])
    assert data["foreign"] == []
    values = data["values"]
    for name in ("objective", "lagrangian", "buffer_size", "updates", "model_version", "constraint/near_origin",
                 "lambda/near_origin", "error_in/near_origin", "error_out/near_origin", "rejected/nan",
                 "rejected/duplicate", "paired"):
        assert name in values, name
    assert values["buffer_size"] >= 0 and data["velocity"] == 0 and data["effort"] == 0


def _feed_with_bad(learner: Learner, tester: RosSide, ns: str,
                   bad: Callable[[list[tuple[str, int, np.ndarray]]], None], rejected: dict[str, int],
                   n: int = 40, logged: tuple[str, ...] | None = None) -> None:
    """Send ``n`` good transitions on ``ns``, calling ``bad(events)`` halfway to inject bad messages; then every
    good one must be paired, ``<ns>/rejected/<reason>`` must equal ``rejected[reason]`` and each of ``logged``
    (default: every reason counted) must be logged as ``rejected/<reason>``."""
    tester.connect(ns)
    ev = episodes(n, np.random.default_rng(3), t0=10**9, interleave=False)
    half = len(ev) // 2
    tester.send(ns, ev[:half])
    bad(ev)
    tester.send(ns, ev[half:])
    tester.wait_received(ns)
    tester.wait(lambda: tester.counter(f"{ns}/paired") == n, 5.0, f"{ns}/paired == {n}")
    tester.wait(lambda: {r: tester.counter(f"{ns}/rejected/{r}") for r in rejected} == rejected, 5.0,
                f"{ns} rejections {rejected}")
    for reason in (logged if logged is not None else [r for r, k in rejected.items() if k]):
        learner.wait_log(f"rejected/{reason}")


def test_nan_and_inf_states_are_rejected_counted_and_logged(shared: tuple[Learner, RosSide, Path]) -> None:
    learner, tester, _ = shared
    ns = "/nan_ns"
    sc = tester.schema

    def bad(ev: list[tuple[str, int, np.ndarray]]) -> None:
        stamp = ev[len(ev) // 2][1]  # the stamp of the next good message: the bad one comes first
        tester.publish(ns, "state", sc.state_to_msg(np.array([np.nan, 0.0]), stamp))
        tester.publish(ns, "state", sc.state_to_msg(np.array([0.1, np.inf]), stamp + DT_NS // 2))

    _feed_with_bad(learner, tester, ns, bad, {"nan": 2})
    assert "is nan" in learner.log() or "is inf" in learner.log()


def test_wrong_length_and_wrong_names_are_rejected(shared: tuple[Learner, RosSide, Path]) -> None:
    from sensor_msgs.msg import JointState

    learner, tester, _ = shared
    ns = "/shape_ns"

    def bad(ev: list[tuple[str, int, np.ndarray]]) -> None:
        stamp = ev[len(ev) // 2][1]
        msg = tester.schema.state_to_msg(np.array([0.1, 0.2]), stamp)
        msg.position = [0.1, 0.2, 0.3]  # three positions for one joint
        tester.publish(ns, "state", msg)
        cmd = tester.schema.control_to_msg(np.array([1.0]), stamp)
        cmd.name = ["cart", "pole"]
        tester.publish(ns, "applied_cmd", cmd)
        tester.publish(ns, "applied_cmd", JointState())  # empty: no names at all

    _feed_with_bad(learner, tester, ns, bad, {"shape": 1, "names": 2})


def test_duplicate_and_out_of_order_stamps_are_rejected(shared: tuple[Learner, RosSide, Path]) -> None:
    learner, tester, _ = shared
    ns = "/order_ns"
    sc = tester.schema

    def bad(ev: list[tuple[str, int, np.ndarray]]) -> None:
        k = len(ev) // 2 - 2
        kind, stamp, vec = ev[k]  # a message already sent: duplicate
        tester.publish(ns, kind, sc.state_to_msg(vec, stamp) if kind == "state" else sc.control_to_msg(vec, stamp))
        first = ev[0]  # an old stamp between two states: out of order
        tester.publish(ns, "applied_cmd", sc.control_to_msg(np.array([0.5]), first[1] + DT_NS // 2))

    _feed_with_bad(learner, tester, ns, bad, {"duplicate": 1, "out_of_order": 1})


def test_absurd_finite_states_and_commands_are_rejected_counted_and_logged(
    shared: tuple[Learner, RosSide, Path],
) -> None:
    """Finite values orders of magnitude beyond the system's plausible range (rejected/bounds), each sent just
    before the good message of the same stamp: every good transition is still paired."""
    learner, tester, _ = shared
    ns = "/absurd_ns"
    sc = tester.schema

    def bad(ev: list[tuple[str, int, np.ndarray]]) -> None:
        stamp = ev[len(ev) // 2][1]
        tester.publish(ns, "state", sc.state_to_msg(np.array([0.1, 4e7]), stamp))
        tester.publish(ns, "applied_cmd", sc.control_to_msg(np.array([-1e12]), stamp))

    _feed_with_bad(learner, tester, ns, bad, {"bounds": 2, "nan": 0})
    assert "outside the plausible range" in learner.log()  # the first of each reason is logged, later ones throttled
    assert tester.counter("rejected/bounds") >= 2  # the learner's totals too


def test_a_single_wild_stamp_is_an_outlier_and_no_good_transition_is_lost(shared: tuple[Learner, RosSide, Path]) -> None:
    """One state stamped 11 days in the future among good ones: counted as an outlier once later states show it out
    of pattern, never taken as a clock restart (which would drop the pending transitions)."""
    learner, tester, _ = shared
    ns = "/wild_ns"

    def bad(ev: list[tuple[str, int, np.ndarray]]) -> None:
        tester.publish(ns, "state", tester.schema.state_to_msg(np.array([0.2, -0.1]), ev[len(ev) // 2][1] + 10**15))

    _feed_with_bad(learner, tester, ns, bad, {"outlier": 1, "out_of_order": 0, "late": 0, "duplicate": 0},
                   logged=())
    learner.wait_log("dropped as outlier(s)")
    assert tester.counter("time_resets") == 0


def test_sigterm_writes_a_final_checkpoint_and_exits_0(shared: tuple[Learner, RosSide, Path]) -> None:
    learner, tester, tmp = shared
    from saml_ros.core.model.checkpoint import CheckpointStore

    assert tester.last().get("updates", 0) > 0
    rc = learner.stop(signal.SIGTERM)
    assert rc == 0, learner.log()
    assert "final checkpoint" in learner.log() or "is current" in learner.log()
    found = CheckpointStore(tmp / "run").load_latest_valid()
    assert found is not None and found.meta["updates"] >= tester.last()["updates"]
    with tester.lock:
        announced = [c.version for c in tester.checkpoints]
    assert announced and announced[-1] == found.version


# ---------------------------------------------------------------------------- configuration errors
def test_unknown_system_and_bad_spec_exit_with_a_clear_message(tmp_path: Path, ros_env: ros_helpers.RosDomain) -> None:
    """Unrecoverable configuration errors: the node logs what is wrong and exits with status 2 (a learner
    that cannot learn should not sit idle looking healthy; a supervisor sees the exit)."""
    bad_spec = tmp_path / "bad_spec.yaml"
    bad_spec.write_text("objective: {loss: l2}\nconstraints:\n- {name: c, region: {box: {x.q: [0, 1]}}, eps: 0.1}\n")
    runs = [
        (Learner(ros_env, {"system": "nosuch", "run_dir": str(tmp_path / "r1")}, ns="/nosuch"),
         ["configuration error", "unknown system 'nosuch'", "friction"]),
        (Learner(ros_env, {"spec_file": str(bad_spec), "run_dir": str(tmp_path / "r2")}),
         ["configuration error", "spec_file", "x.q"]),
        (Learner(ros_env, {"spec_file": str(tmp_path / "missing.yaml"), "run_dir": str(tmp_path / "r3")}),
         ["configuration error", "no such file"]),
    ]
    for learner, expected in runs:
        rc = learner.proc.wait(60)
        log = learner.log()
        assert rc == 2, log
        for text in expected:
            assert text in log, (text, log)


# ---------------------------------------------------------------------------- checkpoints and faults
def _proc_state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text().lower()
    except OSError:
        return "zombie"


def _make_run_dir(run_dir: Path, steps: tuple[int, ...]) -> list[tuple[Path, int, int, float]]:
    """Real checkpoints of a learner trained in-process: ``[(path, version, updates, lambda), ...]``."""
    from saml_ros.core.data.pairing import PairingConfig
    from saml_ros.core.model.checkpoint import CheckpointStore
    from saml_ros.core.online import OnlineConfig, OnlineLearner
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.systems import get_system
    from saml_ros.core.training import TrainConfig

    system = get_system(SYSTEM)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    cfg = OnlineConfig(min_transitions=200, train=TrainConfig(batch_size=128, primal_lr=0.003, dual_lr=0.01))
    learner = OnlineLearner(system, spec, cfg, store=CheckpointStore(run_dir, keep=5))
    src = learner.add_source("/friction", PairingConfig.for_system(system, "next"))
    for kind, stamp, vec in episodes(300, np.random.default_rng(5), t0=10**9, interleave=False):
        learner.ingest(src, kind, stamp, vec)
    out = []
    for n in steps:
        learner.update(n)
        saved = learner.save_checkpoint()
        assert saved is not None
        out.append((saved[0], saved[1], learner.updates, float(learner.lam[0])))
    return out


def test_resume_skips_a_corrupt_checkpoint_and_loads_the_last_good_one(
    tmp_path: Path, ros_env: ros_helpers.RosDomain
) -> None:
    from saml_ros.core.model.checkpoint import atomic_write

    run_dir = tmp_path / "run"
    saved = _make_run_dir(run_dir, (60, 40))  # versions 1 and 2
    good_path, good_version, good_updates, good_lam = saved[-1]
    bad = run_dir / f"ckpt-{good_version + 1:06d}.saml"  # a newer, truncated checkpoint, named by `latest`
    bad.write_bytes(good_path.read_bytes()[: good_path.stat().st_size // 2])
    atomic_write(run_dir / "latest", lambda f: f.write(f"{bad.name} {good_version + 1}\n".encode()))
    learner = Learner(ros_env, dict(BASE_PARAMS, run_dir=str(run_dir), min_transitions=100, checkpoint_period=0.2,
                                    train_threads=2))
    tester = RosSide(ros_env.domain_id)
    try:
        learner.wait_log("resumed from version")
        log = learner.log()
        assert f"skipped {bad}" in log and "truncated" in log
        assert "(2 torch thread(s), subnormals flushed)" in log  # train_threads reached the training process
        tester.wait(lambda: tester.counter("checkpoints_skipped") == 1, 60.0, "checkpoints_skipped == 1")
        assert tester.counter("train_threads") == 2 and tester.counter("train_flush_denormal") == 1
        tester.wait(lambda: bool(tester.last()), 60.0, "the first model_error report")
        first = tester.last()
        assert first["model_version"] == good_version and first["updates"] == good_updates
        assert first["lambda/near_origin"] == good_lam and good_lam > 0
        # it keeps running: new data is paired, training continues, the next checkpoint goes above the bad one
        tester.connect("/friction")
        tester.send("/friction", episodes(150, np.random.default_rng(6), t0=10**9))
        tester.wait_received("/friction")
        tester.wait(lambda: tester.counter("/friction/paired") == 150, 5.0, "150 paired")
        tester.wait(lambda: tester.last().get("model_version", 0) > good_version + 1, 15.0, "a new checkpoint")
        assert tester.last()["updates"] > good_updates
        assert learner.stop() == 0
    finally:
        tester.close()


def test_sigkill_while_checkpointing_then_restart_resumes_and_continues(
    tmp_path: Path, ros_env: ros_helpers.RosDomain
) -> None:
    from saml_ros.core.model.checkpoint import CheckpointStore

    run_dir = tmp_path / "run"
    params = dict(BASE_PARAMS, run_dir=str(run_dir), min_transitions=100, checkpoint_period=0.02)
    tester = RosSide(ros_env.domain_id)
    first_run = Learner(ros_env, params, env=NO_SHM)
    try:
        first_run.wait_log("training starts after")
        tester.connect("/friction")
        tester.send("/friction", episodes(200, np.random.default_rng(7), t0=10**9))
        tester.wait(lambda: tester.counter("checkpoints_written") >= 5 and tester.last().get("updates", 0) > 200,
                    20.0, "training and frequent checkpoints")
        child = int(re.search(r"training process pid (\d+)", first_run.log()).group(1))  # type: ignore[union-attr]
        assert first_run.stop(signal.SIGKILL) == -signal.SIGKILL  # most likely in the middle of a write
        # the training process (which writes the checkpoints) dies with its node
        ros_helpers.wait_for(lambda: not Path(f"/proc/{child}").exists() or "zombie" in _proc_state(child), 10.0,
                             what="the training process to die with the node")
        found = CheckpointStore(run_dir).load_latest_valid()
        assert found is not None
        version, updates = found.version, int(found.meta["updates"])
        lam = float(found.meta["lambda"][0][0])
        assert updates > 0 and lam > 0

        tester.reset()
        second = Learner(ros_env, params, env=NO_SHM)
        second.wait_log(f"resumed from version {version}")
        tester.wait(lambda: tester.last().get("model_version") == version, 60.0, f"model_version {version}")
        resumed = tester.last()
        assert resumed["updates"] == updates and resumed["lambda/near_origin"] == lam
        # the restarted learner continues: more data, the update count grows from the checkpoint's
        tester.connect("/friction")
        tester.send("/friction", episodes(150, np.random.default_rng(8), t0=10**9))
        tester.wait(lambda: tester.last().get("updates", 0) > updates + 100, 20.0, "updates beyond the checkpoint")
        assert second.stop() == 0
        final = CheckpointStore(run_dir).load_latest_valid()
        assert final is not None and final.version > version and final.meta["updates"] > updates + 100
    finally:
        tester.close()


def test_learner_stays_healthy_and_keeps_learning_after_absurd_values_reach_training(
    tmp_path: Path, ros_env: ros_helpers.RosDomain
) -> None:
    """With the plausibility bounds opened (``plausible_bounds``), absurd but finite transitions (1e200 m/s) reach
    the replay buffer: the training steps whose minibatch holds one are skipped (``train_health/*`` on /diagnostics,
    level WARN, never ERROR for health), the others keep training the model, and every checkpoint written is finite and
    records its health."""
    from saml_ros.core.model.checkpoint import CheckpointStore
    from saml_ros.core.model.io import load_model
    from saml_ros.core.systems import get_system

    run_dir = tmp_path / "run"
    params = dict(BASE_PARAMS, run_dir=str(run_dir), min_transitions=200, checkpoint_period=0.5,
                  checkpoint_keep=1000,  # quoted: a -p value is YAML, and this string parameter holds YAML
                  plausible_bounds='"{x.p: [-.inf, .inf], x.v: [-.inf, .inf], u.u: [-.inf, .inf]}"',
                  # every transition trained on: 800 transitions hold ~50 in the constraint's region, and with a fifth
                  # held out the objective / constraint trade-off on ~40 of them moves the error over the whole
                  # distribution by more than what this test measures (that training goes on past absurd values)
                  **{"heldout.fraction": 0.0})
    learner = Learner(ros_env, params)
    tester = RosSide(ros_env.domain_id)
    try:
        learner.wait_log("training starts after", timeout=90.0)
        tester.connect("/friction")
        tester.send("/friction", episodes(400, np.random.default_rng(11), t0=10**9, ep_len=4))
        tester.wait(lambda: tester.counter("model_version") >= 1 and tester.last().get("updates", 0) >= 100, 30.0,
                    "training and a first checkpoint")
        # OK, or WARN from the verdicts alone (a young learner's constraint is "not converged" in training, or not met /
        # unconfirmed / without a verdict on the held-out stretches)
        assert tester.counter("train_health/skipped") == 0 and "skipped" not in tester.diag_message
        assert tester.diag_level == 0 or tester.diag_level == 1 and "constraint 'near_origin'" in tester.diag_message, \
            tester.diag_message
        t = 10**12
        for i in range(4):  # a faulty robot: x_t, u_t and x_t+dt of 1e200 m/s
            x = np.array([0.1, 1e200 if i % 2 else -1e200])
            tester.send("/friction", [("state", t, x), ("applied_cmd", t, np.array([1.0])), ("state", t + DT_NS, x)])
            t += 10 * DT_NS
        tester.wait(lambda: tester.counter("train_health/skipped/loss") > 0 and tester.diag_level >= 1
                    and "training steps skipped" in tester.diag_message, 20.0,
                    "skipped training steps and WARN on /diagnostics")
        tester.send("/friction", episodes(400, np.random.default_rng(12), t0=t + 10 * DT_NS, ep_len=4))
        # enough healthy updates to learn from, whatever the machine's load, counted once every transition is paired
        # (a loaded run's 600 updates left the last checkpoint 12 % below the base model's error; in one loaded CI-like
        # run the last two checkpoints were back near the first's error, with the updates counted from before the
        # second batch was paired: the likeliest cause, not shown)
        tester.wait(lambda: tester.counter("/friction/paired") == 804, 60.0, "all 804 transitions paired")
        tester.wait(lambda: tester.last().get("updates", 0) > 0, 30.0, "a model_error report")
        updates, version = tester.last()["updates"], tester.counter("model_version")
        tester.wait(lambda: tester.last().get("updates", 0) > updates + 3000
                    and tester.counter("model_version") > version + 2, 90.0, "training to go on")
        assert tester.counter("/friction/paired") == 804 and tester.counter("rejected/bounds") == 0
        assert tester.counter("train_health/unhealthy_streak") < 50 and tester.counter("checkpoints_unhealthy") == 0
        # never ERROR for health (most steps stay healthy); the verdicts may say ERROR on their own
        assert all("likely infeasible" in m or "not met" in m for m in tester.error_messages), tester.error_messages[:3]
        assert learner.stop() == 0
    finally:
        tester.close()
    assert "checkpoint not written" not in learner.log()
    store = CheckpointStore(run_dir)
    versions = store.versions()
    assert len(versions) >= 4
    system = get_system(SYSTEM)
    x, u, y = system.make_dataset(2000, np.random.default_rng(13))
    errors = []
    for v in versions:  # no checkpoint with a non-finite weight was ever written
        loaded = load_model(store.path_for(v))
        assert all(bool(np.isfinite(a).all()) for k, a in loaded.arrays.items() if k.startswith("model/")), v
        assert loaded.meta["health"]["healthy"] and loaded.meta["health"]["finite"]
        errors.append(float(np.linalg.norm(loaded.model.predict_np(x, u) - y, axis=1).mean()))
    last = load_model(store.path_for(versions[-1]))
    assert last.meta["health"]["skipped"]["loss"] > 0 and max(last.meta["evidence"]["residual_max"]) > 1e100
    assert errors[-1] < 0.8 * errors[0], errors  # it kept learning after the absurd values arrived
