"""The messages between the learner and its training process (saml_ros.core.online.messages): one frozen dataclass
per kind, pickled across the process boundary, importable without torch, dispatched by type in the training loop."""

from __future__ import annotations

import ast
import dataclasses
import pickle
import threading
from multiprocessing import Pipe
from pathlib import Path
from typing import Any, get_args

import numpy as np
import pytest
from helpers import REPO
from helpers.online import new_learner, transitions, wait_until

from saml_ros.core.online import messages as m
from saml_ros.core.online.loop import LoopConfig, run_loop

EXAMPLES: list[Any] = [
    m.Batch(np.ones((3, 2)), np.zeros((3, 1)), np.full((3, 2), 2.0), np.arange(3.0), np.zeros(3, dtype=np.int64)),
    m.RawMessages([(0, b"\x00\x01"), (1, b"")]),
    m.Pause(), m.Resume(), m.SetLoop(LoopConfig(updates_per_second=5.0)), m.Stop(),
    m.Ready({"path": "p", "version": 2, "updates": 10, "lam": [0.5], "skipped": []}, [8, 8], {"updates": 10.0},
            {"threads": 1, "flush_denormal": True}),
    m.Fatal("resume", "no"), m.Status({"updates": 1.0}, {"/a": {"paired": 3}}, {"checkpoint_write_error": ""}),
    m.Checkpointed("ckpt-000001.saml", 1), m.ErrorReport("training", "boom"), m.Log(20, "text"),
    m.Paused(None, 0, 0), m.Stopped("ckpt-000002.saml", 2, 40),
]


def test_every_kind_is_a_frozen_dataclass_in_one_of_the_two_directions() -> None:
    kinds = {type(e) for e in EXAMPLES}
    assert kinds == set(get_args(m.ToTrainer)) | set(get_args(m.FromTrainer))
    assert not set(get_args(m.ToTrainer)) & set(get_args(m.FromTrainer))
    for kind in kinds:
        assert dataclasses.is_dataclass(kind) and kind.__dataclass_params__.frozen  # type: ignore[attr-defined]


@pytest.mark.parametrize("message", EXAMPLES, ids=lambda e: type(e).__name__)
def test_messages_survive_the_pickling_of_the_socket(message: Any) -> None:
    from multiprocessing.reduction import ForkingPickler

    back = pickle.loads(bytes(ForkingPickler.dumps(message)))  # what Connection.send / recv do
    assert type(back) is type(message)
    for f in dataclasses.fields(message):
        a, b = getattr(message, f.name), getattr(back, f.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b)
        else:
            assert a == b
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(message, dataclasses.fields(message)[0].name if dataclasses.fields(message) else "x", None)


def test_the_messages_module_imports_no_torch() -> None:
    """The learner node imports it before its training interpreter exists (which imports torch meanwhile): its
    imports outside ``TYPE_CHECKING`` are the standard library and numpy."""
    tree = ast.parse(Path(m.__file__).read_text())
    names = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            names.add((node.module or "").split(".")[0])
    assert names == {"__future__", "dataclasses", "typing", "numpy"}, names  # nothing of saml_ros: no cycle
    assert Path(m.__file__).resolve().parent == REPO / "saml_ros" / "core" / "online"


def test_the_training_loop_answers_each_control_message_with_its_type() -> None:
    """Batch goes into the buffer; Pause is answered with Paused, SetLoop changes the pacing, Stop ends the loop
    with Stopped; every status report is a Status."""
    learner = new_learner()
    parent, child = Pipe()
    got: list[Any] = []
    thread = threading.Thread(target=run_loop, args=(learner, LoopConfig(telemetry_rate=50.0), child, got.append),
                              daemon=True, kwargs={"paused": True})
    thread.start()
    trs = transitions(40)
    parent.send(m.Batch(np.stack([t.x for t in trs]), np.stack([t.u for t in trs]), np.stack([t.y for t in trs]),
                        np.array([t.stamp_ns for t in trs]) * 1e-9, np.zeros(len(trs), dtype=np.int64)))
    parent.send(m.SetLoop(LoopConfig(telemetry_rate=20.0)))
    parent.send(m.Pause())
    wait_until(lambda: any(isinstance(g, m.Paused) for g in got))
    parent.send(m.Stop())
    thread.join(30)
    assert not thread.is_alive()
    assert len(learner.buffer) == 40
    kinds = {type(g) for g in got}
    assert kinds == {m.Status, m.Paused, m.Stopped}, kinds
    assert got[-1] == m.Stopped(None, 0, 0)
    assert [g for g in got if isinstance(g, m.Paused)] == [m.Paused(None, 0, 0)]
