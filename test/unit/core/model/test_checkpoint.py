"""Checkpoint files, the run-directory store and torch state flattening (saml_ros.core.model.checkpoint)."""

from __future__ import annotations

import builtins
import io
import json
import math
import pickle
import threading
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from saml_ros.core.model.checkpoint import (
    CheckpointError,
    CheckpointStore,
    arrays_to_torch_state,
    read_checkpoint,
    torch_state_to_arrays,
    write_checkpoint,
)


def sample_arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    w = rng.standard_normal((4, 5))
    w[0, 0] = -0.0
    w[0, 1] = np.nan
    w[0, 2] = -np.inf
    return {
        "model/w": w,
        "model/b": rng.standard_normal(5).astype(np.float32),
        "model/fortran": np.asfortranarray(rng.standard_normal((3, 2))),
        "lambda": np.array([0.25, 0.0]),
        "step": np.array(7, dtype=np.int64),
        "mask": np.array([True, False, True]),
        "bytes": np.arange(10, dtype=np.uint8),
        "c": np.array([1 + 2j, -3j]),
        "empty": np.zeros((0, 3)),
        "big_endian": np.arange(3, dtype=">i4"),
    }


SAMPLE_META: dict[str, Any] = {
    "system": "quadrotor",
    "schema": "0123abcd",
    "hidden": [16, 8],
    "spec": {"name": "selective", "constraints": [{"eps": 0.001, "region": None}]},
    "metrics": {"objective": 1.0e-310, "big": 2**70, "neg": -3},
    "ok": True,
    "unicode": "λ ≤ ε",
}


def assert_same_arrays(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    assert set(got) == set(want)
    for k, a in want.items():
        b = got[k]
        assert b.dtype == a.dtype and b.shape == a.shape, k
        assert b.tobytes(order="C") == a.tobytes(order="C"), k  # bit-exact, NaN payloads and -0.0 included


def rezip(src: Path, dst: Path, edit: Any) -> None:
    """Copy a ZIP with ``edit(name, data) -> data | None`` applied (None drops the member); CRCs are
    recomputed, so the result opens cleanly: only our own checks can catch the change."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for name in zin.namelist():
            data = edit(name, zin.read(name))
            if data is not None:
                zout.writestr(name, data)


def edit_meta(src: Path, dst: Path, change: Any) -> None:
    def edit(name: str, data: bytes) -> bytes:
        if name != "meta.json":
            return data
        doc = json.loads(data)
        change(doc)
        return json.dumps(doc).encode()

    rezip(src, dst, edit)


def cut_points(n: int) -> list[int]:
    """Every offset in the first and last 160 bytes (headers, central directory) and 200 in between."""
    return sorted(set(range(min(n, 160))) | set(range(max(0, n - 160), n)) | set(np.linspace(0, n - 1, 200).astype(int).tolist()))


@pytest.fixture
def good(tmp_path: Path) -> Path:
    path = tmp_path / "good.saml"
    write_checkpoint(path, sample_arrays(), SAMPLE_META)
    return path


# -- single files ------------------------------------------------------------------------------------


def test_round_trip_is_bit_exact(good: Path) -> None:
    arrays, meta = read_checkpoint(good)
    assert_same_arrays(arrays, sample_arrays())
    assert meta == SAMPLE_META
    assert not any(p.name.endswith(".tmp") for p in good.parent.iterdir())


def test_meta_json_details(tmp_path: Path) -> None:
    path = tmp_path / "m.saml"
    write_checkpoint(path, {}, {"t": (1, 2), "nan": math.nan, "inf": -math.inf, "np": np.float32(0.5), "i": np.int64(3)})
    arrays, meta = read_checkpoint(path)
    assert arrays == {}
    assert meta["t"] == [1, 2] and math.isnan(meta["nan"]) and meta["inf"] == -math.inf
    assert meta["np"] == 0.5 and meta["i"] == 3 and type(meta["i"]) is int


def test_write_rejects_bad_input(tmp_path: Path) -> None:
    path = tmp_path / "bad.saml"
    with pytest.raises(ValueError, match="'objs'.*numeric"):
        write_checkpoint(path, {"objs": np.array([object()], dtype=object)}, {})
    with pytest.raises(ValueError, match="'text'.*numeric"):
        write_checkpoint(path, {"text": np.array(["a"])}, {})
    for name in ["", "/abs", "a/../b", "..", "sp ace", "a//b"]:
        with pytest.raises(ValueError, match="not allowed"):
            write_checkpoint(path, {name: np.zeros(1)}, {})
    with pytest.raises(TypeError, match=r"\['opt'\]\['state'\]: key 0"):
        write_checkpoint(path, {}, {"opt": {"state": {0: 1}}})
    with pytest.raises(TypeError, match=r"\['x'\]\[1\]: set"):
        write_checkpoint(path, {}, {"x": [1, {2}]})
    assert list(tmp_path.iterdir()) == []  # nothing written, no temp file left


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match=r"nope\.saml: no such checkpoint file"):
        read_checkpoint(tmp_path / "nope.saml")


def test_empty_and_foreign_files(tmp_path: Path) -> None:
    cases = {
        "empty.saml": (b"", "empty file"),
        "text.saml": (b"hello world\n", "not a ZIP"),
        "npy.saml": (b"\x93NUMPY" + b"\0" * 20, "not a ZIP"),
    }
    for name, (data, msg) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(CheckpointError, match=f"{name}: {msg}"):
            read_checkpoint(tmp_path / name)


class Marker:
    """Unpickling an instance creates (opens for writing) the file ``path``."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        return (builtins.open, (str(self.path), "w"))


def test_payload_is_live(tmp_path: Path) -> None:
    """Guard for the refusal tests below: unpickling our payload really does create the marker."""
    marker = tmp_path / "marker"
    buf = io.BytesIO()
    np.save(buf, np.array([Marker(marker)], dtype=object), allow_pickle=True)
    buf.seek(0)
    np.load(buf, allow_pickle=True)[0].close()  # the unpickled object is the opened file
    assert marker.exists()


def test_pickled_object_array_is_refused_without_running_it(good: Path, tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    evil = np.array([Marker(marker), 1.0], dtype=object)
    npy = io.BytesIO()
    np.save(npy, evil, allow_pickle=True)

    # 1. a checkpoint whose meta lists the array like any other and whose member is an object array
    def swap(name: str, data: bytes) -> bytes:
        return npy.getvalue() if name == "arrays/model/w.npy" else data

    path1 = tmp_path / "object_array.saml"
    rezip(good, path1, swap)
    edit_meta(path1, path1.with_suffix(".2.saml"), lambda d: d["arrays"]["model/w"].update(dtype="|O", shape=[2]))
    # 2. the array member is a raw pickle rather than a .npy
    path3 = tmp_path / "raw_pickle_member.saml"
    rezip(good, path3, lambda n, d: pickle.dumps(Marker(marker)) if n == "arrays/model/w.npy" else d)
    # 3. a numpy .npz made with allow_pickle=True
    path4 = tmp_path / "savez.npz"
    np.savez(path4, w=evil)

    for p, msg in [
        (path1, "'model/w' is an object \\(pickled\\) array"),
        (path1.with_suffix(".2.saml"), "'model/w' is an object \\(pickled\\) array"),
        (path3, "'model/w' is an object \\(pickled\\) array"),
        (path4, "no meta.json member"),
    ]:
        with pytest.raises(CheckpointError, match=f"{p.name}: .*{msg}"):
            read_checkpoint(p)
    assert not marker.exists()


def test_plain_pickle_and_torch_save_are_refused(tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    pkl = tmp_path / "state.pkl"
    pkl.write_bytes(pickle.dumps({"w": Marker(marker)}))
    pt = tmp_path / "model.pt"
    torch.save({"w": torch.ones(3), "evil": Marker(marker)}, pt)
    with pytest.raises(CheckpointError, match="state.pkl: this is a Python pickle"):
        read_checkpoint(pkl)
    with pytest.raises(CheckpointError, match=r"model.pt: no meta.json member \(looks like a torch.save file\)"):
        read_checkpoint(pt)
    assert not marker.exists()


def test_every_truncation_is_refused(good: Path, tmp_path: Path) -> None:
    data = good.read_bytes()
    cut = tmp_path / "cut.saml"
    for n in cut_points(len(data)):
        cut.write_bytes(data[:n])
        with pytest.raises(CheckpointError, match="cut.saml: "):
            read_checkpoint(cut)


def test_every_single_byte_flip_is_refused_or_harmless(good: Path, tmp_path: Path) -> None:
    """Flipping any byte either raises CheckpointError or leaves the content intact (ZIP bookkeeping
    such as timestamps is not covered by any checksum and does not matter)."""
    data = bytearray(good.read_bytes())
    bad = tmp_path / "flip.saml"
    refused = 0
    points = cut_points(len(data))
    for i in points:
        data[i] ^= 0x5A
        bad.write_bytes(data)
        data[i] ^= 0x5A
        try:
            arrays, meta = read_checkpoint(bad)
        except CheckpointError:
            refused += 1
            continue
        assert_same_arrays(arrays, sample_arrays())
        assert meta == SAMPLE_META
    assert refused > len(points) // 2  # the flips did hit checked bytes


def test_checksum_mismatch_when_zip_opens(good: Path, tmp_path: Path) -> None:
    def flip(name: str, data: bytes) -> bytes:
        if name != "arrays/model/w.npy":
            return data
        b = bytearray(data)
        b[-9] ^= 0x01  # last float's mantissa: dtype and shape still parse
        return bytes(b)

    bad = tmp_path / "flipped.saml"
    rezip(good, bad, flip)
    with pytest.raises(CheckpointError, match="flipped.saml: array payload checksum mismatch"):
        read_checkpoint(bad)
    tampered = tmp_path / "meta_tampered.saml"
    edit_meta(good, tampered, lambda d: d["meta"].update(system="friction"))
    with pytest.raises(CheckpointError, match="meta_tampered.saml: metadata checksum mismatch"):
        read_checkpoint(tampered)


@pytest.mark.parametrize(
    ("change", "msg"),
    [
        (lambda d: d.update(format="something.else"), "wrong format name 'something.else'"),
        (lambda d: d.update(format_version=2), r"unsupported format version 2 \(this reader supports \[1\]\)"),
        (lambda d: d.update(format_version="1"), "unsupported format version '1'"),
        (lambda d: d.pop("meta"), "lacks the 'arrays' or 'meta'"),
        (lambda d: d["arrays"].pop("lambda"), r"unexpected \['arrays/lambda.npy'\]"),
        (lambda d: d["arrays"].update(ghost={"dtype": "<f8", "shape": [1]}), r"missing \['arrays/ghost.npy'\]"),
        (lambda d: d["arrays"]["lambda"].update(shape=[3]), "'lambda' is <f8\\[2\\], meta.json says"),
    ],
)
def test_bad_meta_json(good: Path, tmp_path: Path, change: Any, msg: str) -> None:
    bad = tmp_path / "bad.saml"
    edit_meta(good, bad, change)
    with pytest.raises(CheckpointError, match=f"bad.saml: .*{msg}"):
        read_checkpoint(bad)


def test_missing_or_garbled_meta(good: Path, tmp_path: Path) -> None:
    bad = tmp_path / "nometa.saml"
    rezip(good, bad, lambda n, d: None if n == "meta.json" else d)
    with pytest.raises(CheckpointError, match="nometa.saml: no meta.json member; not a saml_ros checkpoint"):
        read_checkpoint(bad)
    bad2 = tmp_path / "garbled.saml"
    rezip(good, bad2, lambda n, d: d[:-10] if n == "meta.json" else d)
    with pytest.raises(CheckpointError, match="garbled.saml: meta.json is not valid UTF-8 JSON"):
        read_checkpoint(bad2)


# -- run directory -----------------------------------------------------------------------------------


def test_store_versions_and_pointer(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path / "run")
    assert store.latest() is None and store.load_latest() is None and store.load_latest_valid() is None
    t0 = time.time()
    for v in range(1, 4):
        path, version = store.save({"w": np.full(3, float(v))}, {"note": f"v{v}"})
        assert version == v and path.name == f"ckpt-{v:06d}.saml"
    assert store.versions() == [1, 2, 3]
    assert store.latest() == (tmp_path / "run" / "ckpt-000003.saml", 3)
    assert (tmp_path / "run" / "latest").read_text() == "ckpt-000003.saml 3\n"
    loaded = store.load_latest()
    assert loaded is not None
    arrays, meta = loaded
    assert arrays["w"].tolist() == [3.0, 3.0, 3.0]
    assert meta["note"] == "v3" and meta["version"] == 3 and t0 <= meta["time"] <= time.time()
    # A new store on the same directory continues the numbering.
    assert CheckpointStore(tmp_path / "run").save({}, {})[1] == 4


def test_malformed_pointer(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path)
    store.save({}, {})
    for text in ["", "garbage", "ckpt-000001.saml 2", "../../etc/passwd 1", "ckpt-000001.saml"]:
        (tmp_path / "latest").write_text(text)
        with pytest.raises(CheckpointError, match="latest: malformed pointer"):
            store.latest()
    assert store.save({}, {})[1] == 2  # a save repairs the pointer
    assert store.latest() == (tmp_path / "ckpt-000002.saml", 2)


def test_pointer_and_files_are_replaced_atomically(tmp_path: Path) -> None:
    """A reader polling load_latest while a writer saves never sees a missing or partial file."""
    store = CheckpointStore(tmp_path, keep=3)
    store.save({"w": np.zeros(20_000)}, {"k": 0})
    stop = threading.Event()
    seen_by: list[list[int]] = []
    errors: list[BaseException] = []

    def reader() -> None:
        reader_store = CheckpointStore(tmp_path)
        seen: list[int] = []
        seen_by.append(seen)
        while not stop.is_set():
            try:
                got = reader_store.load_latest()
                assert got is not None
                arrays, meta = got
                assert np.all(arrays["w"] == meta["k"])
                assert not seen or meta["version"] >= seen[-1]
                seen.append(meta["version"])
            except BaseException as e:  # noqa: BLE001 - reported in the main thread
                errors.append(e)
                return

    threads = [threading.Thread(target=reader) for _ in range(2)]
    for t in threads:
        t.start()
    for k in range(1, 61):
        store.save({"w": np.full(20_000, float(k))}, {"k": k})
    stop.set()
    for t in threads:
        t.join()
    assert not errors, errors[0]
    assert all(len(set(seen)) > 5 for seen in seen_by)  # the readers really raced the writer
    assert store.versions() == [59, 60, 61]


def test_load_latest_valid_falls_back_over_corrupt_files(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path)
    for k in range(3):
        store.save({"w": np.full(100, float(k))}, {"k": k})
    p3 = store.path_for(3)
    p3.write_bytes(p3.read_bytes()[:-100])  # as if the disk lost the tail
    p2 = store.path_for(2)
    p2.write_bytes(b"\x80\x04junk")
    with pytest.raises(CheckpointError, match="ckpt-000003.saml: truncated"):
        store.load_latest()
    res = store.load_latest_valid()
    assert res is not None
    assert res.version == 1 and res.path == store.path_for(1) and res.meta["k"] == 0
    assert np.all(res.arrays["w"] == 0.0)
    assert [p for p, _ in res.skipped] == [p3, p2]
    assert "truncated" in res.skipped[0][1] and "pickle" in res.skipped[1][1]
    # The next save continues after the highest version, never reusing a number.
    assert store.save({}, {})[1] == 4
    store.path_for(1).write_bytes(b"")
    store.path_for(4).write_bytes(b"PK\x03\x04")
    with pytest.raises(CheckpointError, match="no readable checkpoint.*ckpt-000004.*ckpt-000003.*ckpt-000002.*ckpt-000001"):
        store.load_latest_valid()


def test_leftover_temp_files_are_ignored_then_cleaned(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path)
    store.save({"w": np.ones(4)}, {})
    leftovers = [tmp_path / ".ckpt-000002.saml.k3j2h1.tmp", tmp_path / ".latest.x8d9a0.tmp"]
    leftovers[0].write_bytes(b"PK\x03\x04 half a checkpoint")
    leftovers[1].write_bytes(b"ckpt-0000")
    unrelated = tmp_path / "notes.txt"
    unrelated.write_text("keep me")
    assert store.versions() == [1]
    assert store.latest() == (store.path_for(1), 1)
    res = store.load_latest_valid()
    assert res is not None and res.version == 1 and res.skipped == []
    assert store.save({}, {})[1] == 2
    assert not any(p.exists() for p in leftovers)
    assert unrelated.read_text() == "keep me"


def test_pruning_keeps_newest(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path, keep=2)
    for _ in range(5):
        store.save({"w": np.ones(2)}, {})
    assert store.versions() == [4, 5]
    assert store.latest() == (store.path_for(5), 5)
    one = CheckpointStore(tmp_path, keep=1)
    one.save({}, {})
    assert one.versions() == [6] and one.load_latest() is not None
    unpruned = CheckpointStore(tmp_path / "all")
    for _ in range(4):
        unpruned.save({}, {})
    assert unpruned.versions() == [1, 2, 3, 4]
    with pytest.raises(ValueError, match="keep must be >= 1"):
        CheckpointStore(tmp_path, keep=0)


def make_net() -> torch.nn.Module:
    return torch.nn.Sequential(
        torch.nn.Linear(3, 8), torch.nn.BatchNorm1d(8), torch.nn.PReLU(), torch.nn.Linear(8, 2)
    ).double()


@pytest.mark.parametrize(
    "make_opt",
    [
        lambda p: torch.optim.Adam(p, lr=1e-2),
        lambda p: torch.optim.AdamW(p, lr=1e-2, amsgrad=True, betas=(0.8, 0.95)),
        lambda p: torch.optim.SGD(p, lr=1e-2, momentum=0.9, nesterov=True),
    ],
)
def test_torch_state_round_trip_continues_bit_identically(tmp_path: Path, make_opt: Any) -> None:
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(1)
    batches = [(torch.randn(16, 3, generator=gen, dtype=torch.float64), torch.randn(16, 2, generator=gen, dtype=torch.float64)) for _ in range(8)]

    def step(net: torch.nn.Module, opt: torch.optim.Optimizer, xb: torch.Tensor, yb: torch.Tensor) -> None:
        opt.zero_grad()
        torch.nn.functional.mse_loss(net(xb), yb).backward()
        opt.step()

    net = make_net()
    opt = make_opt(net.parameters())
    for xb, yb in batches[:4]:
        step(net, opt, xb, yb)

    a_model, s_model = torch_state_to_arrays("model", net.state_dict())
    a_opt, s_opt = torch_state_to_arrays("optim", opt.state_dict())
    path = tmp_path / "train.saml"
    write_checkpoint(path, {**a_model, **a_opt}, {"torch": {"model": s_model, "optim": s_opt}})
    arrays, meta = read_checkpoint(path)

    torch.manual_seed(123)  # a differently initialised twin
    net2 = make_net()
    opt2 = make_opt(net2.parameters())
    model_state = arrays_to_torch_state(arrays, meta["torch"]["model"])
    opt_state = arrays_to_torch_state(arrays, meta["torch"]["optim"])
    assert list(model_state) == list(net.state_dict())
    assert getattr(model_state, "_metadata", None) == getattr(net.state_dict(), "_metadata", None)
    net2.load_state_dict(model_state)
    opt2.load_state_dict(opt_state)
    assert opt_state["param_groups"] == opt.state_dict()["param_groups"]  # tuples (betas) stay tuples

    for xb, yb in batches[4:]:
        step(net, opt, xb, yb)
        step(net2, opt2, xb, yb)
    for (k, v), v2 in zip(net.state_dict().items(), net2.state_dict().values(), strict=True):
        assert v.dtype == v2.dtype and torch.equal(v, v2), k
    s1, s2 = opt.state_dict()["state"], opt2.state_dict()["state"]
    assert s1.keys() == s2.keys()
    for i in s1:
        for k in s1[i]:
            assert torch.equal(torch.as_tensor(s1[i][k]), torch.as_tensor(s2[i][k])), (i, k)


def test_torch_state_odd_dtypes_and_errors() -> None:
    state: dict[Any, Any] = {
        "bf16": torch.randn(5).to(torch.bfloat16),
        "half": torch.randn(2, 2).half(),
        "step": torch.tensor(3),
        "nested": {"lst": [torch.ones(1), 2, None, "s"], 7: (1.5, float("inf"))},
        "weird key/with spaces": torch.zeros(2),
        "dupe": {"a": torch.ones(1)},
        "dupe.a": torch.zeros(1),
    }
    arrays, skel = torch_state_to_arrays("p", state)
    assert len(arrays) == 7 and all(k.startswith("p/") for k in arrays)
    back: Any = arrays_to_torch_state(arrays, json.loads(json.dumps(skel)))
    assert back["bf16"].dtype == torch.bfloat16 and torch.equal(back["bf16"], state["bf16"])
    assert torch.equal(back["half"], state["half"]) and back["step"].dtype == torch.int64
    assert back["nested"][7] == (1.5, float("inf")) and back["nested"]["lst"][1:] == [2, None, "s"]
    assert torch.equal(back["dupe.a"], torch.zeros(1)) and torch.equal(back["dupe"]["a"], torch.ones(1))
    with pytest.raises(TypeError, match=r"p/x: cannot store a set"):
        torch_state_to_arrays("p", {"x": {1}})
    with pytest.raises(CheckpointError, match="array 'p/bf16' is missing"):
        arrays_to_torch_state({}, skel)
