"""The demo's pictures (PNG, matplotlib Agg): trajectories of base, learned and oracle from the same starts, the
live model error over simulated time with the checkpoint swaps and roll backs marked, and the per-start landing
errors of the paired evaluation."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.offline.plots import save_figure

#: colour of each arm in every picture
COLORS = {"base": "tab:red", "SA": "tab:blue", "UA": "tab:green", "oracle": "black"}


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectories(xs: Mapping[str, np.ndarray], pad: np.ndarray, path: Path, dt: float = 0.1,
                      title: str = "") -> Path:
    """Height over time (whole episode and the last 3.5 s near the pad) and the top view of the same starts for
    each arm; ``xs[arm]`` ``(K, steps + 1, 13)`` true states, the same K starts for every arm."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    ax_h, ax_z, ax_xy = axes
    for arm, traj in xs.items():
        c = COLORS.get(arm, None)
        t = np.arange(traj.shape[1]) * dt
        for k in range(traj.shape[0]):
            kw = {"color": c, "alpha": 0.8, "lw": 1.2, "label": arm if k == 0 else None}
            ls = "--" if arm == "oracle" else "-"
            ax_h.plot(t, traj[k, :, 2], ls, **kw)
            ax_z.plot(t, traj[k, :, 2] - pad[2], ls, **kw)
            ax_xy.plot(traj[k, :, 0], traj[k, :, 1], ls, **kw)
            ax_xy.plot(traj[k, 0, 0], traj[k, 0, 1], "o", color=c, ms=3)
    for ax in (ax_h, ax_z):
        ax.axhline(pad[2] if ax is ax_h else 0.0, color="gray", lw=0.8, ls=":")
        ax.set_xlabel("time (s)")
    ax_h.set_ylabel("height pz (m)")
    ax_h.set_title("height over time (pad at the dotted line)")
    t_end = (next(iter(xs.values())).shape[1] - 1) * dt
    ax_z.set_xlim(max(0.0, t_end - 3.5), t_end)
    ax_z.set_ylim(-0.05, 0.35)
    ax_z.set_ylabel("height above the pad (m)")
    ax_z.set_title("near the pad: base settles above it, learned / oracle on it")
    ax_xy.plot(pad[0], pad[1], "*", color="gold", ms=14, mec="k", label="pad")
    ax_xy.set_aspect("equal", adjustable="datalim")
    ax_xy.set_xlabel("x (m)")
    ax_xy.set_ylabel("y (m)")
    ax_xy.set_title("top view (o = start)")
    ax_h.legend(loc="upper right", fontsize=8)
    ax_xy.legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_live_error(status_log: Sequence[tuple[float, int, float, float, float]],
                    episodes: Sequence[Any], path: Path, smooth: int = 10) -> Path:
    """Top: the MPC's live one-step squared error of the model in use vs f_hat's on the same transitions (the
    monitor's window means from ``mpc/status``), checkpoint swaps as vertical lines, roll backs (a version drop)
    in red. Bottom: each live episode's landing error by its end time, coloured by whether it flew f_hat or a
    learned model."""
    plt = _plt()
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(11, 6.4), sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    if status_log:
        a = np.array(status_log, dtype=np.float64)
        t = a[:, 0] - a[0, 0]
        for col, label, c in ((2, "model in use", "tab:blue"), (3, "base model f_hat", "tab:red")):
            y = a[:, col]
            ok = np.isfinite(y)
            if ok.any():
                ys = np.convolve(np.where(ok, y, 0.0), np.ones(smooth), "same") / np.maximum(
                    np.convolve(ok.astype(float), np.ones(smooth), "same"), 1.0)
                ax.semilogy(t[ok], np.maximum(ys[ok], 1e-7), color=c, lw=1.0, label=f"live error, {label}")
        versions = a[:, 1].astype(int)
        change = np.flatnonzero(np.diff(versions)) + 1
        for i in change:
            back = versions[i] < versions[i - 1]
            ax.axvline(t[i], color="red" if back else "gray", lw=1.4 if back else 0.8, ls="-" if back else "--")
            ax.text(t[i], 1.02, f"{'roll back ' if back else ''}v{versions[i]}", rotation=90, va="bottom",
                    ha="center", fontsize=7, color="red" if back else "dimgray", transform=ax.get_xaxis_transform())
        t0 = a[0, 0]
    else:
        t0 = 0.0
    ax.set_ylabel("one-step squared error")
    ax.set_title("live model error over simulated time (dashed: checkpoint swapped in; red: roll back)", pad=28)
    ax.legend(loc="upper right", fontsize=8)
    if episodes:
        te = np.array([e.t_end - t0 for e in episodes])
        err = np.array([e.error for e in episodes])
        learned = np.array([e.model_first > 0 for e in episodes])
        ax2.semilogy(te[~learned], np.maximum(err[~learned], 1e-4), "o", color="tab:red", ms=4,
                     label="episode on f_hat")
        ax2.semilogy(te[learned], np.maximum(err[learned], 1e-4), "o", color="tab:blue", ms=4,
                     label="episode on a learned model")
        ax2.legend(loc="upper right", fontsize=8)
    ax2.set_ylabel("landing error (m)")
    ax2.set_xlabel("simulated time (s)")
    fig.tight_layout()
    return save_figure(fig, path)


def plot_paired(pairs: Mapping[str, tuple[np.ndarray, np.ndarray]], path: Path, arm: str = "SA") -> Path:
    """Per-start landing error, base (x) vs ``arm`` (y), one marker set per start set (e.g. standard and
    aggressive starts); below the diagonal = the learned model landed closer."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.6, 5.2))
    lo, hi = 1e-4, 1e-4
    for (name, (b, m)), mk in zip(pairs.items(), ("o", "^", "s")):
        b, m = np.maximum(b, 1e-4), np.maximum(m, 1e-4)
        ax.loglog(b, m, mk, ms=5, alpha=0.75, label=f"{name} starts ({np.mean(m < b):.0%} better)")
        hi = max(hi, float(b.max()), float(m.max()))
    ax.plot([lo, hi * 1.5], [lo, hi * 1.5], color="gray", lw=0.8)
    ax.axhline(1.0, color="red", lw=0.8, ls=":")
    ax.set_xlabel("landing error, base model f_hat (m)")
    ax.set_ylabel(f"landing error, learned ({arm}, guarded) (m)")
    ax.set_title("paired evaluation: one marker per start")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)
