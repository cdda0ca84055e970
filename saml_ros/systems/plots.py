"""Figures of the systems' hidden effects: the friction profile mu(p) and the ground-effect gain K_ground.

Run ``./dev python -m saml_ros.systems.plots OUTDIR`` (the repo keeps its copies in ``docs/figures/``).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from numpy.typing import ArrayLike  # noqa: E402

from saml_ros.systems.friction.model import FRICTION_PROFILES, FrictionDoubleIntegrator  # noqa: E402
from saml_ros.systems.quadrotor.model import Quadrotor, ground_effect_factor  # noqa: E402


def plot_friction(path: Path, systems: dict[str, FrictionDoubleIntegrator] | None = None) -> Path:
    """Write mu(p) (m/s^2) and b(p) = dt mu(p) (m/s) over the sampled positions [-2, 2] m to ``path``, one curve
    per system (default: every named profile of :data:`FRICTION_PROFILES`)."""
    if systems is None:
        systems = {name: FrictionDoubleIntegrator(profile=name) for name in FRICTION_PROFILES}
    p = torch.linspace(-2.0, 2.0, 801, dtype=torch.float64)
    fig, ax = plt.subplots(figsize=(6.4, 3.6), constrained_layout=True)
    ax.axvspan(-0.5, 0.5, color="tab:orange", alpha=0.15, label="accuracy region |p| <= 0.5 m")
    top = 0.0
    for (name, sys_), color in zip(systems.items(), ("tab:blue", "tab:green", "tab:purple", "tab:red")):
        mu = sys_.friction_decel(p).numpy()
        top = max(top, float(mu.max()))
        ax.plot(p.numpy(), mu, color=color, lw=2, label=f"{name}: mu(p)")
    dt = next(iter(systems.values())).dt
    ax.set_xlabel("position p (m)")
    ax.set_ylabel("friction deceleration mu(p) (m/s^2)")
    ax.set_ylim(0.0, 1.35 * top)

    def to_b(m: ArrayLike) -> np.ndarray:
        return np.asarray(m) * dt

    def to_mu(b: ArrayLike) -> np.ndarray:
        return np.asarray(b) / dt

    sec = ax.secondary_yaxis("right", functions=(to_b, to_mu))
    sec.set_ylabel(f"b(p) = dt mu(p) (m/s), dt = {dt:g} s")
    ax.set_title("Double integrator: position-varying kinetic friction (named profiles)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper center", ncol=3, fontsize=7)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_ground_effect(path: Path, system: Quadrotor | None = None) -> Path:
    """Write a heat map of K_ground(theta, h_prop) (and a level-hover slice) to ``path``."""
    quad = system or Quadrotor()
    theta = torch.linspace(0.0, 0.6 * math.pi, 217, dtype=torch.float64)  # K = 0 beyond pi/2
    h = torch.linspace(0.0, 2.0, 201, dtype=torch.float64)
    k = ground_effect_factor(h[:, None], theta[None, :], quad.h_max, quad.alpha).numpy()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10.0, 3.8), constrained_layout=True,
                                  gridspec_kw={"width_ratios": [1.6, 1.0]})
    im = ax.pcolormesh(np.degrees(theta.numpy()), h.numpy(), k, shading="auto", cmap="viridis")
    ax.contour(np.degrees(theta.numpy()), h.numpy(), k, levels=[0.05, 0.1, 0.2, 0.3, 0.4],
               colors="white", linewidths=0.7)
    ax.axvline(np.degrees(0.4), color="tab:red", ls="--", lw=1, label="max tilt in training data (0.4 rad)")
    ax.set_xlabel("theta_ground: tilt of body -z from world -z (deg)")
    ax.set_ylabel("propeller height h_prop (m)")
    ax.set_title(f"K_ground(theta, h_prop), h_max = {quad.h_max:g} m, alpha = {quad.alpha:g}")
    ax.legend(loc="upper right", fontsize=8)
    fig.colorbar(im, ax=ax, label="K_ground (added thrust fraction)")
    for deg in (0.0, 0.2, 0.4):
        kk = ground_effect_factor(h, torch.tensor(deg, dtype=torch.float64), quad.h_max, quad.alpha)
        ax2.plot(h.numpy(), kk.numpy(), label=f"theta = {deg:g} rad")
    ax2.set_xlabel("propeller height h_prop (m)")
    ax2.set_ylabel("K_ground")
    ax2.set_title("slices")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_figures(outdir: str | Path) -> list[Path]:
    """Write ``friction_profile.png`` and ``ground_effect.png`` into ``outdir`` (created); returns the paths."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    return [plot_friction(out / "friction_profile.png"), plot_ground_effect(out / "ground_effect.png")]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("outdir", help="folder to write the PNG figures into")
    for path in write_figures(ap.parse_args(argv).outdir):
        print(path)


if __name__ == "__main__":
    main()
