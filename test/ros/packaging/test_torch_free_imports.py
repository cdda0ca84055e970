"""What runs without torch: importing torch costs a process 2-3 CPU-s (most of a node's start-up), so the processes
that neither train nor evaluate a network import it only where they do.

* the learner node's own process: its parameters, configure's checks, the training process's setup (sent pickled),
  the telemetry it assembles; the training process it starts imports torch;
* ``bringup`` (its monitor builds the system) and anything that only builds a system or its problem spec;
* ``train`` refusing a run before it reads any data (a missing bag): torch comes once the data is read;
* the MPC node until its first checkpoint: it plans with f_hat in numpy and CasADi; loading a network imports
  torch (``nodes.runtime.single_torch_thread`` sets its thread count before that);
* the simulators: the paddle ball's MuJoCo world, the numpy twins of the friction and quadrotor true dynamics.

Each check runs in a fresh interpreter (the test process has torch imported already), so these tests start
processes and live under test/ros/. A change that pulls torch back into one of these paths fails here, naming the
step and the first module that imported it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from helpers import REPO

#: run in a fresh interpreter: each step, then the check that torch is still not imported
PROBE = r'''
import importlib.abc, sys, traceback

first = []


class Watch(importlib.abc.MetaPathFinder):
    """Records the import stack of the first ``import torch`` (and lets it happen)."""

    def find_spec(self, name, path=None, target=None):
        if name == "torch" and not first:
            first.extend(f"{f.filename}:{f.lineno}" for f in traceback.extract_stack()[:-1]
                         if "importlib" not in f.filename and "<frozen" not in f.filename)
        return None


sys.meta_path.insert(0, Watch())


def check(step):
    assert "torch" not in sys.modules, f"{step} imported torch: " + " <- ".join(reversed(first[-8:]))
    print("ok", step, flush=True)


STEPS = sys.argv[1].split(",")
if "learner" in STEPS:
    import pickle

    import saml_ros.nodes.learner  # noqa: F401
    from msg_schemas import get_schema
    from msg_schemas.decode import make_decoder
    from saml_ros.core.online import assemble_telemetry
    from saml_ros.core.online.config import LearnerConfig, learner_params

    values = {p.name: p.default for p in learner_params()} | {"system": "friction"}
    config, system, spec = LearnerConfig.validated(values, "/friction")
    schema = get_schema("friction")
    channels = [(0, kind, topic) for _, kind, topic, _ in config.channels(schema)]
    setup = config.training_setup(system, spec, schema.target_pairing, sys.argv[2], channels, make_decoder)
    pickle.dumps(setup)
    assemble_telemetry(spec.constraint_names, {}, {})
    check("learner")
if "systems" in STEPS:
    import saml_ros.bringup.monitor  # noqa: F401
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.systems import get_entry, system_names

    for name in system_names():
        built = get_entry(name).make_system()
        ProblemSpec.for_system(built.paper_spec(), built)
        built.plausible_state()
    check("systems")
if "train_refused" in STEPS:
    from saml_ros.offline.cli import main

    assert main(["--system", "friction", "--bag", sys.argv[2] + "/no_such_bag"]) == 2
    check("train_refused")
if "mpc" in STEPS:
    import time

    import numpy as np

    import saml_ros.nodes.mpc
    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.core.mpc.service import MPCService
    from saml_ros.nodes.runtime import single_torch_thread

    single_torch_thread()  # what the node's main does first


    class Log:
        def info(self, text):
            pass

        warning = error = info


    for name in ("friction", "quadrotor", "paddle_ball", "examples/diff_drive/system.yaml"):
        key = "system_file" if name.endswith(".yaml") else "system"
        params = {key: sys.argv[3] + "/" + name if key == "system_file" else name,
                  "run_dir": sys.argv[2] + "/mpc_" + name.replace("/", "_")}
        service = MPCService(MPCConfig.from_params(params), lambda u, stamp: None, Log())
        service.start()
        robot = service.system
        x = robot.hover_state() if hasattr(robot, "hover_state") else np.zeros(robot.state.size)
        answer = service.receive(x, 10**9, time.perf_counter())
        service.stop()
        assert answer is not None, name
    check("mpc")
    import torch  # what the first checkpoint brings: one thread, as set before it came

    assert torch.get_num_threads() == 1, torch.get_num_threads()
    print("ok torch_threads", flush=True)
if "sims" in STEPS:
    import importlib

    from saml_ros.core.systems import get_entry
    from sim_nodes.binding import COMMON_PARAMS, config_from_params
    from saml_ros.core.worlds.sim_core import APPLIED, FLIGHT, STATE

    for node in ("paddle_ball_sim", "friction_sim", "quadrotor_sim"):
        binding = importlib.import_module("sim_nodes." + node).BINDING
        values = {p.name: p.default for p in (*COMMON_PARAMS, *binding.params)}
        entry = get_entry(binding.system)
        core = entry.simulator(entry.make_system(), config_from_params(values), values)
        outputs = core.begin(0, 0) + [o for k in range(1, 30) for o in core.tick(k * 20_000_000)]
        kinds = {kind for kind, _, _ in outputs}
        # it simulated: a bounce of the ball, commands applied to the time-stepped systems
        assert ({STATE, APPLIED, FLIGHT} if node == "paddle_ball_sim" else {STATE, APPLIED}) <= kinds, outputs
    check("sims")
'''


def _probe(steps: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p),
               MUJOCO_GL="disable")
    return subprocess.run([sys.executable, "-c", PROBE, steps, str(tmp_path), str(REPO)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)


def test_the_learner_node_bringup_and_a_refused_train_run_import_no_torch(tmp_path: Path) -> None:
    out = _probe("learner,systems,train_refused", tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.split() == ["ok", "learner", "ok", "systems", "ok", "train_refused"], out.stdout + out.stderr


def test_the_mpc_node_plans_with_f_hat_without_torch(tmp_path: Path) -> None:
    """The MPC node imports torch with its first checkpoint, not before: its module, and for each built-in system
    and a robot of a system file, configuring its service and answering a state with f_hat import no torch."""
    out = _probe("mpc", tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.split() == ["ok", "mpc", "ok", "torch_threads"], out.stdout + out.stderr


def test_the_simulators_import_no_torch(tmp_path: Path) -> None:
    """Each simulator node's core steps its world without torch: the paddle ball's MuJoCo world, and the numpy
    twins of the friction and quadrotor true dynamics (equal to ``true_step`` to rounding: test_sim_core.py)."""
    out = _probe("sims", tmp_path)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.split() == ["ok", "sims"], out.stdout + out.stderr


def test_the_probe_sees_torch_where_it_is_imported(tmp_path: Path) -> None:
    """The check can fail: building the network (what the training process does) imports torch, and the probe
    names the step."""
    probe = PROBE.replace('if "learner" in STEPS:', 'if "network" in STEPS:\n'
                          '    from saml_ros.core.model.network import DynamicsModel  # noqa: F401\n'
                          '    check("network")\nif "learner" in STEPS:', 1)
    env = dict(os.environ, PYTHONPATH=str(REPO), MUJOCO_GL="disable")
    out = subprocess.run([sys.executable, "-c", probe, "network", str(tmp_path)], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "network imported torch" in out.stderr, out.stdout + out.stderr
