"""ReplayBuffer: eviction policies, validation, thread safety, memory bound (saml_ros.core.data.buffer)."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest

from saml_ros.core.data.buffer import ReplayBuffer


def rows(start: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Transitions numbered start..start+n-1 whose x, u, y all encode their number k: x = [k, k, k],
    u = [-k], y = [2k, 2k] (so a torn row is detectable)."""
    k = np.arange(start, start + n, dtype=np.float64)[:, None]
    return np.repeat(k, 3, axis=1), -k, np.repeat(2 * k, 2, axis=1)


def test_fifo_keeps_the_newest_in_order() -> None:
    buf = ReplayBuffer(5, 3, 1, 2, policy="fifo")
    x, u, y = rows(0, 3)
    for i in range(3):
        assert buf.add(x[i], u[i], y[i], stamp=0.1 * i, source=i % 2)
    assert len(buf) == 3 and buf.total_evicted == 0
    assert buf.add_batch(*rows(3, 4), stamp=np.arange(3, 7) * 0.1, source=np.array([0, 1, 0, 1])) == 4
    got = buf.arrays()
    assert got.seq.tolist() == [2, 3, 4, 5, 6]  # 0 and 1 evicted first
    assert got.x[:, 0].tolist() == [2, 3, 4, 5, 6]
    assert np.array_equal(got.u[:, 0], -got.x[:, 0]) and np.array_equal(got.y[:, 1], 2 * got.x[:, 0])
    assert np.allclose(got.stamp, [0.2, 0.3, 0.4, 0.5, 0.6]) and got.source.tolist() == [0, 0, 1, 0, 1]
    assert (len(buf), buf.total_added, buf.total_evicted, buf.total_discarded) == (5, 7, 2, 0)
    # A batch larger than the capacity keeps its last `capacity` rows.
    buf.add_batch(*rows(100, 12))
    assert buf.arrays().x[:, 0].tolist() == [107, 108, 109, 110, 111]
    assert (buf.total_added, buf.total_evicted) == (19, 14)
    # Single adds continue the ring in order.
    for k in range(200, 203):
        buf.add(*(a[0] for a in rows(k, 1)))
    assert buf.arrays().x[:, 0].tolist() == [110, 111, 200, 201, 202]


def test_capacity_bound_and_counters() -> None:
    rng = np.random.default_rng(0)
    for policy in ("fifo", "reservoir"):
        buf = ReplayBuffer(37, 3, 1, 2, policy=policy, seed=1)
        added = 0
        for _ in range(60):
            n = int(rng.integers(0, 9))
            buf.add_batch(*rows(added, n))
            added += n
            assert len(buf) == min(added, 37)
            assert buf.total_added == added == len(buf) + buf.total_evicted + buf.total_discarded
        got = buf.arrays()
        assert got.x.shape == (37, 3) and len(np.unique(got.seq)) == 37
        assert np.array_equal(got.x[:, 0], got.seq)  # every stored row is intact and labelled right


def test_reservoir_is_a_uniform_sample() -> None:
    """A 500-row reservoir over 10000 arrivals holds about 50 from each tenth of the stream
    (hypergeometric sd ~ 6.5; 5 sd allowed); FIFO would hold all 500 in the last tenth."""
    cap, n = 500, 10_000
    single = ReplayBuffer(cap, 3, 1, 2, policy="reservoir", seed=7)
    x, u, y = rows(0, n)
    for i in range(n):
        single.add(x[i], u[i], y[i])
    batched = ReplayBuffer(cap, 3, 1, 2, policy="reservoir", seed=7)
    chunks = np.random.default_rng(3).integers(1, 700, size=200).cumsum()
    for a, b in zip(np.r_[0, chunks], chunks, strict=False):
        if a < n:
            batched.add_batch(x[a : min(b, n)], u[a : min(b, n)], y[a : min(b, n)])
    for buf in (single, batched):
        seq = buf.arrays().seq
        assert len(seq) == cap and len(np.unique(seq)) == cap
        counts = np.bincount(seq // (n // 10), minlength=10)
        assert counts.sum() == cap and np.all(np.abs(counts - cap // 10) < 33), counts
        assert (buf.total_evicted + buf.total_discarded) == n - cap


def test_reservoir_inclusion_probability_per_item() -> None:
    """P(item i is stored after n arrivals) = capacity / n for the first, a middle and the last item."""
    cap, n, trials = 10, 100, 3000
    hits = np.zeros(n)
    x, u, y = rows(0, n)
    for t in range(trials):
        buf = ReplayBuffer(cap, 3, 1, 2, policy="reservoir", seed=t)
        buf.add_batch(x, u, y)
        hits[buf.arrays().seq] += 1
    p = hits / trials  # each ~ Binomial(3000, 0.1)/3000, sd 0.0055
    assert np.all(np.abs(p[[0, 1, 50, 98, 99]] - 0.1) < 0.03), p[[0, 1, 50, 98, 99]]
    assert abs(p.mean() - 0.1) < 1e-12


def test_reservoir_is_reproducible_with_a_seed() -> None:
    a = ReplayBuffer(8, 3, 1, 2, policy="reservoir", seed=42)
    b = ReplayBuffer(8, 3, 1, 2, policy="reservoir", seed=42)
    c = ReplayBuffer(8, 3, 1, 2, policy="reservoir", seed=43)
    for buf in (a, b, c):
        buf.add_batch(*rows(0, 500))
    assert np.array_equal(a.arrays().seq, b.arrays().seq)
    assert not np.array_equal(a.arrays().seq, c.arrays().seq)


def test_sample_is_uniform_with_replacement() -> None:
    buf = ReplayBuffer(50, 3, 1, 2)
    with pytest.raises(ValueError, match="empty replay buffer"):
        buf.sample(4, np.random.default_rng(0))
    buf.add_batch(*rows(0, 20))
    rng = np.random.default_rng(1)
    x, u, y = buf.sample(40_000, rng)
    assert x.shape == (40_000, 3) and u.shape == (40_000, 1) and y.shape == (40_000, 2) and x.dtype == np.float64
    assert np.array_equal(u[:, 0], -x[:, 0]) and np.array_equal(y[:, 0], 2 * x[:, 0])
    counts = np.bincount(x[:, 0].astype(int), minlength=20)
    assert len(counts) == 20 and np.all(np.abs(counts - 2000) < 250), counts  # only stored rows, uniformly
    x[:] = -1  # a copy: the buffer is untouched
    assert buf.arrays().x.min() == 0
    with pytest.raises(ValueError, match="batch_size must be >= 1"):
        buf.sample(0, rng)


def test_rejects_bad_input_with_clear_messages() -> None:
    buf = ReplayBuffer(10, 3, 1, 2)
    good_x, good_u, good_y = np.zeros(3), np.zeros(1), np.zeros(2)
    cases: list[tuple[tuple[Any, ...], dict[str, Any], str]] = [
        ((np.zeros(4), good_u, good_y), {}, r"x has shape \(4,\); expected \(3,\)"),
        ((good_x, np.zeros((1, 1)), good_y), {}, r"u has shape \(1, 1\); expected \(1,\)"),
        ((good_x, good_u, [0.0, np.nan]), {}, r"y\[1\] is nan \(non-finite\)"),
        (([0.0, np.inf, 0.0], good_u, good_y), {}, r"x\[1\] is inf"),
        ((good_x, ["a"], good_y), {}, "u has dtype <U1; expected real numbers"),
        ((good_x, good_u, [[1.0], [1.0, 2.0]]), {}, "y is not a numeric array"),
        ((good_x, good_u, good_y), {"stamp": float("nan")}, "stamp is non-finite"),
        ((good_x, good_u, good_y), {"stamp": [1.0, 2.0]}, "stamp must be a number"),
        ((good_x, good_u, good_y), {"source": -1}, "source must be >= 0"),
        ((good_x, good_u, good_y), {"source": 1.5}, "source must be an int"),
    ]
    for args, kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            buf.add(*args, **kw)
    bx, bu, by = rows(0, 5)
    by[3, 1] = np.nan
    by[4, 0] = -np.inf
    batch_cases: list[tuple[tuple[Any, ...], dict[str, Any], str]] = [
        ((bx, bu, by), {}, r"y\[3, 1\] is nan \(non-finite\) \(2 bad rows in the batch\)"),
        ((bx, bu[:4], by), {}, r"u has shape \(4, 1\); expected \(5, 1\)"),
        ((bx[:, :2], bu, by), {}, r"x has shape \(5, 2\); expected \(B, 3\)"),
        ((bx[0], bu, by), {}, r"x has shape \(3,\); expected \(B, 3\)"),
        ((bx, bu, np.zeros((5, 2))), {"stamp": np.zeros(4)}, r"stamp must be a number or shape \(5,\)"),
        ((bx, bu, np.zeros((5, 2))), {"source": np.array([0, 1, 2, 3, -4])}, "source must be >= 0, got -4"),
    ]
    for args, kw, msg in batch_cases:
        with pytest.raises(ValueError, match=msg):
            buf.add_batch(*args, **kw)
    assert len(buf) == 0 and buf.total_added == 0  # nothing of a rejected call is stored
    with pytest.raises(ValueError, match="unknown eviction policy 'lifo'"):
        ReplayBuffer(10, 3, 1, 2, policy="lifo")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="capacity must be >= 1"):
        ReplayBuffer(0, 3, 1, 2)


def test_zero_width_control_and_empty_batch() -> None:
    buf = ReplayBuffer(4, 2, 0, 2)
    assert buf.add([1.0, 2.0], [], [3.0, 4.0])
    assert buf.add_batch(np.zeros((0, 2)), np.zeros((0, 0)), np.zeros((0, 2))) == 0
    x, u, y = buf.sample(3, np.random.default_rng(0))
    assert u.shape == (3, 0) and np.all(x == [1.0, 2.0])


def test_memory_is_fixed() -> None:
    for policy in ("fifo", "reservoir"):
        buf = ReplayBuffer(1000, 13, 4, 13, policy=policy, seed=0)
        expected = 1000 * (13 + 4 + 13 + 1) * 8 + 1000 * 2 * 8  # float rows, stamp, source + seq int64
        assert buf.nbytes == expected
        storage = [buf._x, buf._u, buf._y, buf._stamp, buf._source, buf._seq]
        x = np.random.default_rng(0).standard_normal((5000, 13))
        for _ in range(10):
            buf.add_batch(x, x[:, :4], x)
        for i in range(100):
            buf.add(x[i], x[i, :4], x[i])
        assert buf.total_added == 50_100 and len(buf) == 1000
        assert buf.nbytes == expected
        # The same arrays, never reallocated.
        assert all(a is b for a, b in zip(storage, [buf._x, buf._u, buf._y, buf._stamp, buf._source, buf._seq], strict=True))


@pytest.mark.parametrize("policy", ["fifo", "reservoir"])
def test_concurrent_add_and_sample(policy: str) -> None:
    """A writer (single adds and batches) and two samplers: no exception, no torn row, exact counters."""
    buf = ReplayBuffer(256, 3, 1, 2, policy=policy, seed=0)  # type: ignore[arg-type]
    buf.add_batch(*rows(0, 1))
    stop = threading.Event()
    errors: list[BaseException] = []
    sampled = [0, 0]

    def sampler(i: int) -> None:
        rng = np.random.default_rng(i)
        try:
            while not stop.is_set():
                x, u, y = buf.sample(64, rng)
                k = x[:, 0]
                assert np.all(x == k[:, None]) and np.all(u[:, 0] == -k) and np.all(y == 2 * k[:, None])
                got = buf.arrays()
                assert np.array_equal(got.x[:, 0], got.seq) and np.all(np.diff(got.seq) > 0)
                sampled[i] += 1
        except BaseException as e:  # noqa: BLE001 - reported in the main thread
            errors.append(e)

    threads = [threading.Thread(target=sampler, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    k = 1
    for j in range(3000):
        if j % 3:
            x, u, y = rows(k, 1)
            buf.add(x[0], u[0], y[0], stamp=float(k))
            k += 1
        else:
            buf.add_batch(*rows(k, 7))
            k += 7
    stop.set()
    for t in threads:
        t.join()
    assert not errors, errors[0]
    assert min(sampled) > 10
    assert buf.total_added == k and len(buf) == 256
    assert buf.total_added == len(buf) + buf.total_evicted + buf.total_discarded
