"""Fixed-memory replay buffer of transitions (x_t, u_t, y) for online learning (``docs/buffer.md``)."""

from __future__ import annotations

import threading
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

Policy = Literal["fifo", "reservoir"]


class Transitions(NamedTuple):
    """Stored rows, copies (``N`` = number of rows).

    Attributes:
        x: ``(N, n_x)`` float64 state x_t.
        u: ``(N, n_u)`` float64 applied control u_t.
        y: ``(N, n_y)`` float64 target (x_{t+1}, or the system's target vector).
        stamp: ``(N,)`` float64 stamp of x_t in seconds.
        source: ``(N,)`` int64 index of the robot / simulator the transition came from.
        seq: ``(N,)`` int64 arrival number (0 = the first transition ever added).
    """

    x: np.ndarray
    u: np.ndarray
    y: np.ndarray
    stamp: np.ndarray
    source: np.ndarray
    seq: np.ndarray


class ReplayBuffer:
    """Thread-safe store of at most ``capacity`` transitions in preallocated numpy arrays.

    Memory is allocated once (``nbytes``) and never grows. When the buffer is full, a new transition
    is handled by the eviction policy:

    - ``"fifo"``: ring buffer; the new transition overwrites the oldest one, so the buffer always holds
      the ``capacity`` most recent transitions (tracks a drifting system, forgets old regions).
    - ``"reservoir"``: Vitter's algorithm R; the n-th transition (n counted from 1 over the buffer's
      life) is kept with probability ``capacity / n`` and then replaces a uniformly chosen stored row,
      otherwise it is discarded. At any time the buffer is a uniform random sample (without
      replacement) of every transition ever added (keeps early, rare regions; adapts slowly).
      Random choices come from ``numpy.random.default_rng(seed)``: the same seed and the same sequence
      of ``add``/``add_batch`` calls give the same contents.

    ``sample`` draws uniformly with replacement over the stored rows. Every method takes one lock,
    so one thread may add (a ROS callback) while another samples (a trainer); a sampled row is never
    half-written. Invalid input raises ``ValueError`` naming the array, the row/column and the
    problem, and nothing of that call is stored.

    Counters: ``total_added`` = ``len(self) + total_evicted + total_discarded``; ``total_evicted``
    counts stored rows that were overwritten, ``total_discarded`` counts reservoir arrivals that were
    never stored (always 0 for FIFO).

    Args:
        capacity: maximum number of stored transitions (>= 1).
        n_x, n_u, n_y: widths of x, u and y (>= 1 for x and y, >= 0 for u).
        policy: ``"fifo"`` or ``"reservoir"``.
        seed: seed of the reservoir's random generator (unused by FIFO).
    """

    def __init__(
        self, capacity: int, n_x: int, n_u: int, n_y: int, policy: Policy = "fifo", seed: int | None = None
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if n_x < 1 or n_u < 0 or n_y < 1:
            raise ValueError(f"bad widths n_x={n_x}, n_u={n_u}, n_y={n_y}")
        if policy not in ("fifo", "reservoir"):
            raise ValueError(f"unknown eviction policy {policy!r}; use 'fifo' or 'reservoir'")
        self._capacity = int(capacity)
        self.n_x, self.n_u, self.n_y = int(n_x), int(n_u), int(n_y)
        self.policy: Policy = policy
        self._rng = np.random.default_rng(seed)
        self._x = np.zeros((capacity, n_x))
        self._u = np.zeros((capacity, n_u))
        self._y = np.zeros((capacity, n_y))
        self._stamp = np.zeros(capacity)
        self._source = np.zeros(capacity, dtype=np.int64)
        self._seq = np.zeros(capacity, dtype=np.int64)
        self._total = 0
        self._evicted = 0
        self._discarded = 0
        self._lock = threading.Lock()

    # -- counters ----------------------------------------------------------------------------------

    @property
    def capacity(self) -> int:
        return self._capacity

    def __len__(self) -> int:
        with self._lock:
            return min(self._total, self._capacity)

    @property
    def total_added(self) -> int:
        """Transitions accepted by ``add``/``add_batch`` over the buffer's life."""
        with self._lock:
            return self._total

    @property
    def total_evicted(self) -> int:
        """Stored transitions that were later overwritten."""
        with self._lock:
            return self._evicted

    @property
    def total_discarded(self) -> int:
        """Reservoir arrivals that were never stored."""
        with self._lock:
            return self._discarded

    @property
    def nbytes(self) -> int:
        """Bytes of the preallocated row storage (constant)."""
        return sum(a.nbytes for a in (self._x, self._u, self._y, self._stamp, self._source, self._seq))

    def __repr__(self) -> str:
        return (
            f"ReplayBuffer({len(self)}/{self._capacity} rows, policy={self.policy!r}, "
            f"n_x={self.n_x}, n_u={self.n_u}, n_y={self.n_y}, total_added={self.total_added})"
        )

    # -- writing -----------------------------------------------------------------------------------

    def add(self, x: ArrayLike, u: ArrayLike, y: ArrayLike, *, stamp: float = 0.0, source: int = 0) -> bool:
        """Add one transition: ``x (n_x,)``, ``u (n_u,)``, ``y (n_y,)``, stamp in seconds, source index.

        Returns:
            True if it was stored (always for FIFO), False if the reservoir discarded it.

        Raises:
            ValueError: wrong shape, non-numeric or non-finite values, bad stamp or source.
        """
        xs = _rows("x", x, self.n_x, single=True)
        us = _rows("u", u, self.n_u, single=True)
        ys = _rows("y", y, self.n_y, single=True)
        st = _stamps(stamp, 1, single=True)
        so = _sources(source, 1, single=True)
        return self._insert(xs, us, ys, st, so) == 1

    def add_batch(
        self,
        x: ArrayLike,
        u: ArrayLike,
        y: ArrayLike,
        *,
        stamp: ArrayLike = 0.0,
        source: ArrayLike = 0,
    ) -> int:
        """Add ``B`` transitions in arrival order: ``x (B, n_x)``, ``u (B, n_u)``, ``y (B, n_y)``;
        ``stamp`` and ``source`` are scalars (shared) or ``(B,)``.

        The whole batch is validated first; a bad row rejects the whole batch.

        Returns:
            how many of the ``B`` rows are stored after the call.

        Raises:
            ValueError: as :meth:`add`, naming the first bad row.
        """
        xs = _rows("x", x, self.n_x, single=False)
        n = xs.shape[0]
        us = _rows("u", u, self.n_u, single=False, batch=n)
        ys = _rows("y", y, self.n_y, single=False, batch=n)
        st = _stamps(stamp, n, single=False)
        so = _sources(source, n, single=False)
        return self._insert(xs, us, ys, st, so)

    def _insert(self, x: np.ndarray, u: np.ndarray, y: np.ndarray, stamp: np.ndarray, source: np.ndarray) -> int:
        b = x.shape[0]
        if b == 0:
            return 0
        cap = self._capacity
        with self._lock:
            seq = self._total + np.arange(b, dtype=np.int64)
            if self.policy == "fifo":
                keep = np.arange(max(0, b - cap), b)  # rows older than the last `cap` are overwritten anyway
                slots = seq[keep] % cap
                self._evicted += max(0, self._total + b - cap) - max(0, self._total - cap)
            else:
                slots = np.where(seq < cap, seq, -1)
                late = seq >= cap
                if late.any():
                    j = self._rng.integers(0, seq[late] + 1)  # algorithm R: j ~ U{0, ..., n-1}
                    slots[late] = np.where(j < cap, j, -1)
                    self._evicted += int(np.count_nonzero(j < cap))
                    self._discarded += int(np.count_nonzero(j >= cap))
                # Sequential semantics: when two rows of this batch pick the same slot, the later wins.
                rev_slots = slots[::-1]
                _, first = np.unique(rev_slots, return_index=True)
                keep = np.sort(b - 1 - first)
                keep = keep[slots[keep] >= 0]
                slots = slots[keep]
            self._x[slots] = x[keep]
            self._u[slots] = u[keep]
            self._y[slots] = y[keep]
            self._stamp[slots] = stamp[keep]
            self._source[slots] = source[keep]
            self._seq[slots] = seq[keep]
            self._total += b
            return int(keep.size)

    # -- reading -----------------------------------------------------------------------------------

    def sample(self, batch_size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Draw ``batch_size`` stored rows uniformly with replacement.

        Returns:
            copies ``x (batch_size, n_x)``, ``u (batch_size, n_u)``, ``y (batch_size, n_y)``, float64.

        Raises:
            ValueError: the buffer is empty or ``batch_size < 1``.
        """
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        with self._lock:
            n = min(self._total, self._capacity)
            if n == 0:
                raise ValueError("cannot sample from an empty replay buffer")
            idx = rng.integers(0, n, size=batch_size)
            return self._x[idx], self._u[idx], self._y[idx]

    def arrays(self) -> Transitions:
        """Copies of all stored rows, oldest arrival first."""
        with self._lock:
            n = min(self._total, self._capacity)
            order = np.argsort(self._seq[:n], kind="stable")
            return Transitions(
                self._x[order], self._u[order], self._y[order], self._stamp[order], self._source[order], self._seq[order]
            )


# -- validation --------------------------------------------------------------------------------------


def _rows(name: str, value: ArrayLike, width: int, *, single: bool, batch: int | None = None) -> np.ndarray:
    """Validate and return a ``(B, width)`` float64 array (``B = 1`` for a single row)."""
    try:
        a = np.asarray(value)
    except (ValueError, TypeError) as e:  # ragged nested lists
        raise ValueError(f"{name} is not a numeric array ({e})") from None
    if a.dtype.kind not in "iuf":
        raise ValueError(f"{name} has dtype {a.dtype}; expected real numbers")
    want = f"({width},)" if single else f"(B, {width})" if batch is None else f"({batch}, {width})"
    ok = a.shape == (width,) if single else a.ndim == 2 and a.shape[1] == width
    if not ok or (batch is not None and a.shape[0] != batch):
        raise ValueError(f"{name} has shape {a.shape}; expected {want}")
    a = a.astype(np.float64)
    if single:
        a = a[None, :]
    finite = np.isfinite(a)
    if not finite.all():
        r, c = np.argwhere(~finite)[0]
        bad = int(np.count_nonzero(~finite.all(axis=1)))
        where = f"{name}[{c}]" if single else f"{name}[{r}, {c}]"
        more = "" if single else f" ({bad} bad row{'s' if bad > 1 else ''} in the batch)"
        raise ValueError(f"{where} is {a[r, c]} (non-finite){more}")
    return a


def _stamps(value: ArrayLike, n: int, *, single: bool) -> np.ndarray:
    a = np.asarray(value)
    if a.dtype.kind not in "iuf" or (a.ndim != 0 and (single or a.shape != (n,))):
        raise ValueError(f"stamp must be a number{'' if single else f' or shape ({n},)'}, got {value!r:.80}")
    a = np.broadcast_to(a.astype(np.float64), (n,))
    if not np.isfinite(a).all():
        raise ValueError(f"stamp is non-finite ({a[~np.isfinite(a)][0]})")
    return a


def _sources(value: ArrayLike, n: int, *, single: bool) -> np.ndarray:
    a = np.asarray(value)
    if a.dtype.kind not in "iu" or (a.ndim != 0 and (single or a.shape != (n,))):
        raise ValueError(f"source must be an int{'' if single else f' or int array of shape ({n},)'}, got {value!r:.80}")
    if (a < 0).any():
        raise ValueError(f"source must be >= 0, got {a[a < 0].ravel()[0]}")
    return np.broadcast_to(a.astype(np.int64), (n,))
