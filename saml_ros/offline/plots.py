"""Figures: training curves (the paper's primal-dual training-curve figure), held-out error comparisons and
the double-integrator error map. Matplotlib with the Agg backend; every function writes one PNG."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from saml_ros.core.training import History

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from saml_ros.core.dynamics.system import System
    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.offline.pipelines import Comparison


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _band(ax: Any, x: np.ndarray, y: np.ndarray, label: str, color: str | None = None) -> None:
    """Mean over ensemble members (last axis) with a min-max band."""
    y = y.reshape(len(x), -1)
    line, = ax.plot(x, y.mean(1), label=label, color=color)
    if y.shape[1] > 1:
        ax.fill_between(x, y.min(1), y.max(1), alpha=0.2, color=line.get_color())


def plot_training_curves(histories: Mapping[str, History], path: str | Path, title: str = "",
                         marks: Mapping[str, float] | None = None) -> Path:
    """Objective, each constraint g_k (0 = the bound) and each lambda_k against epochs, one colour per run;
    ``marks``: label -> epoch of a vertical line on every panel (e.g. where training starts aiming below eps)."""
    plt = _plt()
    names = sorted({n for h in histories.values() for n in h.constraint_names})
    rows = 1 + (2 if names else 0)
    fig, axes = plt.subplots(rows, 1, figsize=(8, 2.6 * rows), sharex=True, squeeze=False)
    ax_obj = axes[0, 0]
    for label, h in histories.items():
        a = h.as_arrays()
        if len(a["epoch"]) == 0:
            continue
        _band(ax_obj, a["epoch"], a["objective"], label)
        for k, n in enumerate(h.constraint_names):
            _band(axes[1, 0], a["epoch"], a["constraints"][..., k], f"{label}: g[{n}]")
            _band(axes[2, 0], a["epoch"], a["lambdas"][..., k], f"{label}: lambda[{n}]")
    ax_obj.set_ylabel("objective (minibatch)")
    ax_obj.set_yscale("log")
    ax_obj.legend(fontsize=8)
    for text, epoch in (marks or {}).items():
        for ax in axes[:, 0]:
            ax.axvline(epoch, color="grey", ls="--", lw=1, label=text if ax is axes[-1, 0] else None)
    if names:
        axes[1, 0].axhline(0.0, color="red", ls=":", lw=1)
        axes[1, 0].set_ylabel("constraint g = E[l] - eps")
        axes[1, 0].legend(fontsize=8)
        axes[2, 0].set_ylabel("dual variable lambda")
        axes[2, 0].legend(fontsize=8)
    axes[-1, 0].set_xlabel("epoch")
    fig.suptitle(title or "primal-dual training (mean over seeds, band = min..max)")
    fig.tight_layout()
    return save_figure(fig, path)


def plot_comparison(cmp: Comparison, path: str | Path) -> Path:
    """Bar chart of held-out error inside / outside / overall for SA vs UA, with per-seed dots."""
    plt = _plt()
    regs = list(zip(cmp.eval_uniform.regions, cmp.eval_sufficient.regions))
    fig, axes = plt.subplots(1, len(regs), figsize=(6 * len(regs), 4), squeeze=False)
    for ax, (ru, rs) in zip(axes[0], regs):
        groups = ["inside region", "outside region", "overall"]
        for j, (label, r, color) in enumerate((("Uniformly Accurate", ru, "tab:gray"),
                                               ("Sufficiently Accurate", rs, "tab:blue"))):
            vals = [r.inside, r.outside, r.overall]
            xs = np.arange(3) + (j - 0.5) * 0.38
            ax.bar(xs, [float(np.mean(v)) for v in vals], width=0.36, label=label, color=color, alpha=0.8)
            for xi, v in zip(xs, vals):
                ax.plot(np.full(len(v), xi), v, "k.", ms=4)
        ax.set_xticks(np.arange(3), groups)
        ax.set_ylabel(f"held-out error ({cmp.spec.constraints[0].loss})" if cmp.spec.constraints else "error")
        ax.set_title(f"{cmp.system}: constraint '{ru.name}' ({100 * ru.frac_inside:.1f}% of test data inside)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_error_map(
    system: System, models: Mapping[str, DynamicsModel], path: str | Path, u: float = 1.0,
    p_range: tuple[float, float] = (-2.0, 2.0), v_range: tuple[float, float] = (-2.5, 2.5), n: int = 161,
    box: float | None = 0.5,
) -> Path:
    """Double integrator: |v error| of f_hat + phi against the true model over (p, v) at constant u
    (the paper's model-error figure), one panel per model, the accuracy region drawn as a box."""
    plt = _plt()
    p, v = np.meshgrid(np.linspace(*p_range, n), np.linspace(*v_range, n))
    x = np.stack([p.ravel(), v.ravel()], 1)
    uu = np.full((len(x), 1), u)
    truth = system.true_step_np(x, uu)
    errs = {k: np.abs(m.predict_np(x, uu)[:, 1] - truth[:, 1]).reshape(p.shape) for k, m in models.items()}
    vmax = max(float(e.max()) for e in errs.values())
    fig, axes = plt.subplots(1, len(errs), figsize=(5.2 * len(errs), 4.2), squeeze=False)
    im = None
    for ax, (label, e) in zip(axes[0], errs.items()):
        im = ax.pcolormesh(p, v, e, shading="auto", vmin=0, vmax=vmax, cmap="viridis")
        if box:
            ax.plot([-box, box, box, -box, -box], [-box, -box, box, box, -box], "r--", lw=1)
        inside = (np.abs(p) <= box) & (np.abs(v) <= box) if box else np.zeros_like(p, bool)
        sub = f"mean {e.mean():.3f}, inside box {e[inside].mean():.3f}" if box else f"mean {e.mean():.3f}"
        ax.set_title(f"{label}\n{sub}", fontsize=10)
        ax.set_xlabel("p (m)")
        ax.set_ylabel("v (m/s)")
    fig.colorbar(im, ax=axes[0].tolist(), label=f"|v error| (m/s) at u = {u:g} m/s²")
    return save_figure(fig, path)


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` as a PNG (110 dpi) to ``path`` (parent directories created), close it; returns the path."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
