"""Primal-dual training speed (issue #6): ``./dev python -m bench.bench_train [--full-grid] [--profile]``.

Prints, each measured in this one run (see docs/performance.md for what each number means):

1. **throughput**: samples/s of ``PrimalDualTrainer.fit`` (fast engine: with the fused C++ kernel, and its torch
   path ``engine="fast_torch"``; each also as us/step, % of the one-thread ceiling and ratio to the paper loop)
   against a plain per-minibatch PyTorch loop written as the paper describes Algorithm 1 (``nn.Sequential`` of Linear/PReLU, zero-initialised last
   layer, ``torch.optim.Adam`` for theta and for lambda; per step: sample indices, forward, loss + lambda * g,
   backward, step, dual step, clamp), for the 16-8 net at quadrotor sizes and the 128-128 paddle-ball net,
   batch 256. The two alternate in short rounds; the ratio uses each one's best round (a shared, noisy machine
   only ever slows a round down) and the median ratio is printed too. A timed ``fit`` runs ``--fit-epochs`` epochs
   (default 50: a training run's steady state; the paper's quadrotor run is one fit of 3000 epochs), and the
   5-epoch fits this bench timed before are printed beside it (they count a fit's fixed costs, evaluation and
   diagnosis at its end, 10x as often).
2. **many models at once**: (a) 15 seeds of the paper's friction setting as one ensemble against one after
   another; (b) the paper's convergence grid (nets 2-1, 4-2, 8-4, 16-8 x N in {100, 1000, 5000, 10000, 15000}
   x 15 datasets, sigma = 0.2 noise on v, Sufficiently Accurate spec, 200 epochs, batch 128), each (net, N)
   cell's 15 datasets trained as one ensemble, against one-by-one training.
3. **arithmetic ceiling**: FLOPs per sample of each net against this machine's measured float32 matmul rate.

Threads: one intra-op thread by default (``--threads``): the machine has two cores shared with other work, and
PyTorch's intra-op parallelism slows these tiny operations down (measured: ~30x slower per step with 2 threads
while another process was busy). Both sides of every ratio run with the same setting.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import torch
from torch import nn

from saml_ros.core.dynamics.system import System
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, Transitions

GRID_NETS: tuple[tuple[int, int], ...] = ((2, 1), (4, 2), (8, 4), (16, 8))
GRID_N: tuple[int, ...] = (100, 1000, 5000, 10000, 15000)
GRID_DATASETS = 15
GRID_EPOCHS = 200  # the paper's double-integrator setting
GRID_BATCH = 128  # the paper does not state M; TrainConfig's default


def _say(msg: str = "") -> None:
    print(msg, flush=True)


# ------------------------------------------------------------------------------------------------- helpers
@dataclass
class Problem:
    """One dataset, spec and network size, with the tensors a plain loop needs (float32, float64 masks)."""

    name: str
    system: System
    spec: ProblemSpec
    hidden: tuple[int, ...]
    x: np.ndarray
    u: np.ndarray
    y: np.ndarray


def make_problem(name: str, system_name: str, hidden: tuple[int, ...], n: int, seed: int = 0) -> Problem:
    system = get_system(system_name)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    x, u, y = system.make_dataset(n, np.random.default_rng(seed))
    return Problem(name, system, spec, hidden, x, u, y)


def make_trainer(p: Problem, cfg: TrainConfig, n_models: int = 1, seed: int = 0) -> tuple[PrimalDualTrainer,
                                                                                             Transitions]:
    model = DynamicsModel(p.system, p.hidden, n_models=n_models, seed=seed)
    model.fit_normalization(p.x, p.u, p.y)
    tr = PrimalDualTrainer(model, p.spec, cfg)
    return tr, Transitions(model, p.spec, p.x, p.u, p.y)


class PaperLoop:
    """The plain loop: Algorithm 1 as the paper describes it, with the spec's losses written out by hand.

    Inputs are pre-normalised, f_hat and region masks precomputed (the loop does the least work it can).
    """

    def __init__(self, p: Problem, batch: int, seed: int = 0) -> None:
        model = DynamicsModel(p.system, p.hidden)
        model.fit_normalization(p.x, p.u, p.y)
        data = Transitions(model, p.spec, p.x, p.u, p.y)
        with torch.no_grad():
            self.z = ((torch.cat([data.x, data.u], -1) - model.in_mean[0]) / model.in_std[0]).contiguous()
        self.y, self.base, self.ostd = data.y, data.base, model.out_std[0]
        terms = [p.spec.objective, *p.spec.constraints]
        self.terms = terms
        self.masks = [None if m is None else m.float() for m in data.masks]
        self.ny = [torch.linalg.vector_norm(self.y[:, list(t.fields)], dim=-1).clamp_min(1e-9) for t in terms]
        dims = [self.z.shape[1], *p.hidden, self.y.shape[1]]
        layers: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
            layers.append(nn.Linear(a, b))
            if i < len(dims) - 2:
                layers.append(nn.PReLU())
        self.net = nn.Sequential(*layers)
        last = self.net[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.lam = nn.Parameter(torch.zeros(len(terms) - 1))
        self.opt = torch.optim.Adam(self.net.parameters(), lr=1e-3)
        self.dual_opt = torch.optim.Adam([self.lam], lr=1e-4, maximize=True)
        self.batch = batch
        self.n = self.z.shape[0]
        self.gen = torch.Generator().manual_seed(seed)

    def _loss(self, j: int, e: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        t = self.terms[j]
        ef = e[:, list(t.fields)]
        if t.loss == "squared_l2":
            return (ef * ef).sum(-1)
        if t.loss == "l2":
            return torch.linalg.vector_norm(ef, dim=-1)
        if t.loss == "normalized":
            return torch.linalg.vector_norm(ef, dim=-1) / self.ny[j][idx]
        raise ValueError(f"the paper loop has no {t.loss} loss")

    def _estimate(self, j: int, loss: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        t, m = self.terms[j], self.masks[j]
        if m is None:
            return loss.mean() - t.eps
        mb = m[idx]
        if t.mean == "unconditional":
            return (loss * mb).mean() - t.eps
        return (loss * mb).sum() / mb.sum().clamp_min(1.0) - t.eps

    def run(self, steps: int) -> None:
        for _ in range(steps):
            idx = torch.randint(0, self.n, (self.batch,), generator=self.gen)
            pred = self.net(self.z[idx]) * self.ostd + self.base[idx]
            e = pred - self.y[idx]
            f = self._estimate(0, self._loss(0, e, idx), idx)
            g = torch.stack([self._estimate(j, self._loss(j, e, idx), idx) for j in range(1, len(self.terms))])
            lagrangian = f + (self.lam.detach() * g).sum()
            self.opt.zero_grad(set_to_none=True)
            lagrangian.backward()
            self.opt.step()
            self.lam.grad = g.detach()
            self.dual_opt.step()
            with torch.no_grad():
                self.lam.clamp_(min=0.0)


def interleaved(fns: dict[str, Callable[[], tuple[float, float]]], rounds: int) -> dict[str, list[tuple[float, float]]]:
    """Each function returns (wall, CPU) seconds per unit of work; they run alternately, ``rounds`` times each."""
    out: dict[str, list[tuple[float, float]]] = {k: [] for k in fns}
    for _ in range(rounds):
        for k, f in fns.items():
            out[k].append(f())
    return out


def _per_step(run: Callable[[int], Any], arg: int, steps: int) -> tuple[float, float]:
    """(wall, CPU) seconds per step of ``run(arg)``, which makes ``steps`` steps."""
    wall, cpu = timed2(partial(run, arg))
    return wall / steps, cpu / steps


def timed(f: Callable[[], Any]) -> float:
    """Wall-clock seconds of ``f()``."""
    return timed2(f)[0]


def timed2(f: Callable[[], Any]) -> tuple[float, float]:
    """Wall-clock and this thread's CPU seconds of ``f()`` (the CPU time excludes time spent descheduled, which
    on this shared machine is the main source of noise; with one intra-op thread it is the work done)."""
    t0, c0 = time.perf_counter(), time.thread_time()
    f()
    return time.perf_counter() - t0, time.thread_time() - c0


# ------------------------------------------------------------------------------------------------- 1 throughput
THROUGHPUT_CASES = (
    # name, system, hidden, batch, samples, plain steps per round
    ("16-8 (quadrotor: 17 in, 13 out)", "quadrotor", (16, 8), 256, 256 * 40, 200),
    ("128-128 (paddle ball: 12 in, 3 out)", "paddle_ball", (128, 128), 256, 256 * 20, 60),
)


def flops_per_sample(system: System, hidden: tuple[int, ...]) -> int:
    """Forward + backward matmul FLOPs per sample (~3x the forward's) of a net on ``system``."""
    dims = [system.state.size + system.control.size, *hidden, system.target.size]
    return 3 * sum(2 * a * b for a, b in zip(dims[:-1], dims[1:]))


def bench_throughput(rounds: int, profile: bool, fit_epochs: int = 50) -> dict[str, float]:
    """Returns the fast engine's best samples/s per case.

    Each timed ``fit`` of the fast engine runs ``fit_epochs`` epochs, a training run's steady state (the paper's
    quadrotor run is one fit of 3000 epochs): a fit's fixed costs (state exchange, end-of-fit evaluation and
    diagnosis) are paid once per fit, and a 5-epoch fit counts them 600 times as often as that run does. The
    5-epoch figure is printed too. The paper loop has no per-run cost in its rounds, so its ``plain_steps``
    steps per round are its steady state."""
    from saml_ros.core.training.engines import fused

    _say("== 1. training throughput: saml_ros (fast engine) vs the paper's plain loop, one model, batch 256 ==")
    t0 = time.perf_counter()
    kernel = fused.load_kernel()
    status = ("ready (built in %.0f s)" % (time.perf_counter() - t0) if fused.build_seconds() else "ready (cached)") \
        if kernel is not None else f"not built ({fused.kernel_reason()}): both fast rows run the torch path"
    _say(f"   fused training kernel: {status}")
    r1 = matmul_rate(1)
    _say(f"   one-thread ceiling: torch.mm 2048x2048 float32 at {r1 / 1e9:.1f} GFLOP/s, measured now")
    achieved = {}
    for name, sysname, hidden, batch, n, plain_steps in THROUGHPUT_CASES:
        p = make_problem(name, sysname, hidden, n)
        plain = PaperLoop(p, batch)
        fast, data = make_trainer(p, TrainConfig.paper(batch_size=batch, engine="fast"))
        fast_t, data_t = make_trainer(p, TrainConfig.paper(batch_size=batch, engine="fast_torch"))
        ours_plain, data_p = make_trainer(p, TrainConfig.paper(batch_size=batch, engine="plain"))
        per_epoch = n // batch
        epochs = max(1, fit_epochs)
        short = max(1, plain_steps // per_epoch)  # the fit length this bench timed before (5 epochs of 16-8)
        plain.run(20)
        fast.fit(data, epochs=1)
        fast_t.fit(data_t, epochs=1)
        ours_plain.fit(data_p, epochs=1)
        res = interleaved(
            {
                "paper loop": partial(_per_step, plain.run, plain_steps, plain_steps),
                "saml_ros fast": partial(_per_step, partial(fast.fit, data), epochs, epochs * per_epoch),
                f"fast, {short}-epoch fits": partial(_per_step, partial(fast.fit, data), short, short * per_epoch),
                "fast, torch path": partial(_per_step, partial(fast_t.fit, data_t), epochs, epochs * per_epoch),
                "saml_ros plain engine": partial(_per_step, partial(ours_plain.fit, data_p), 1, per_epoch),
            },
            rounds,
        )
        assert fast.engine_used == "fast" and ours_plain.engine_used == "plain" and not fast_t.kernel_used
        _say(f"-- {name}, batch {batch}, {n} samples; {rounds} interleaved rounds; fits of {epochs} epochs "
             f"({epochs * per_epoch} steps) unless stated; per step: best wall-clock (median) / best CPU time")
        wall = {k: [w for w, _ in v] for k, v in res.items()}
        cpu = {k: [c for _, c in v] for k, v in res.items()}
        for k in res:
            _say(f"   {k:24s} {min(wall[k]) * 1e6:7.1f} us ({statistics.median(wall[k]) * 1e6:7.1f}) "
                 f"= {batch / min(wall[k]) / 1e6:6.3f} M samples/s | CPU {min(cpu[k]) * 1e6:7.1f} us "
                 f"= {batch / min(cpu[k]) / 1e6:6.3f} M samples/s")
        r_wall = min(wall["paper loop"]) / min(wall["saml_ros fast"])
        r_med = statistics.median(a / b for a, b in zip(wall["paper loop"], wall["saml_ros fast"]))
        r_cpu = min(cpu["paper loop"]) / min(cpu["saml_ros fast"])
        r_eng = min(cpu["saml_ros plain engine"]) / min(cpu["saml_ros fast"])
        _say(f"   RATIO fast / paper loop: {r_wall:.2f}x wall-clock (best rounds; median of per-round ratios "
             f"{r_med:.2f}x), {r_cpu:.2f}x CPU time; fast / saml_ros plain engine: {r_eng:.2f}x CPU time")
        ceil_us = batch * flops_per_sample(p.system, hidden) / r1 * 1e6  # us per step at the ceiling
        for label, key, on in (("kernel    ", "saml_ros fast", fast.kernel_used),
                               (f"kernel, {short}-epoch fits", f"fast, {short}-epoch fits", fast.kernel_used),
                               ("torch path", "fast, torch path", True)):
            if not on:
                _say(f"   {label}: not built, see above")
                continue
            us = min(wall[key]) * 1e6
            _say(f"   {label}: {us:7.1f} us/step = {100 * ceil_us / us:5.2f}% of the 1-thread ceiling "
                 f"({ceil_us:.1f} us/step); {min(wall['paper loop']) * 1e6 / us:5.2f}x the paper's plain loop "
                 f"(best rounds)")
        achieved[name] = batch / min(wall["saml_ros fast"])
        if profile:
            profile_step(fast, data, plain)
    return achieved


def profile_step(fast: PrimalDualTrainer, data: Transitions, plain: PaperLoop) -> None:
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as tprofile

    for label, fn in (("saml_ros fast, 1 epoch", lambda: fast.fit(data, epochs=1)),
                      ("paper loop, 40 steps", lambda: plain.run(40))):
        with tprofile(activities=[ProfilerActivity.CPU]) as prof:
            fn()
        _say(f"   profile ({label}; self CPU time, profiler overhead included):")
        table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=14)
        for line in table.splitlines():
            _say("     " + line)


# ------------------------------------------------------------------------------------------------- 2a seeds
def bench_seeds(n_seeds: int, epochs: int) -> float:
    _say(f"== 2a. {n_seeds} seeds of one configuration (friction, 4-2 net, 15000 samples, batch 128, "
         f"{epochs} epochs) ==")
    system = get_system("friction")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    seeds = list(range(n_seeds))
    parts = [system.make_dataset(15000, np.random.default_rng(s)) for s in seeds]
    x, u, y = (np.stack([q[i] for q in parts]) for i in range(3))
    times = {}
    for engine in ("fast", "plain"):
        cfg = TrainConfig.paper(epochs=epochs, batch_size=128, engine=engine)
        times[f"ensemble of {n_seeds}, {engine} engine"] = _train_group(system, spec, x, u, y, cfg, seeds, (4, 2))[0]
        times[f"one by one, {engine} engine"] = sum(
            _train_group(system, spec, x[i : i + 1], u[i : i + 1], y[i : i + 1], cfg, [s], (4, 2))[0]
            for i, s in enumerate(seeds)
        )
    for k, v in times.items():
        _say(f"   {k:28s} {v:7.2f} s")
    r_plain = times["one by one, plain engine"] / times[f"ensemble of {n_seeds}, fast engine"]
    r_fast = times["one by one, fast engine"] / times[f"ensemble of {n_seeds}, fast engine"]
    _say(f"   RATIO one-by-one (plain engine) / ensemble (fast engine): {r_plain:.1f}x;"
         f" one-by-one (fast engine) / ensemble (fast engine): {r_fast:.1f}x")
    return r_plain


def _train_group(system: System, spec: ProblemSpec, x: np.ndarray, u: np.ndarray, y: np.ndarray,
                 cfg: TrainConfig, seeds: Sequence[int], hidden: tuple[int, ...]) -> tuple[float, PrimalDualTrainer,
                                                                                          Transitions]:
    """Seconds of ``fit`` for an ensemble with one member per seed and per-member datasets ``(E, N, .)``."""
    from saml_ros.offline.pipelines import train_models

    tm = train_models(system, spec, x, u, y, cfg, list(seeds), hidden)
    data = Transitions(tm.model, spec, x, u, y)
    return tm.train_seconds, tm.trainer, data


# ------------------------------------------------------------------------------------------------- 2b grid
def grid_data(system: System, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    parts = [system.make_dataset(n, np.random.default_rng([n, k]), {"v": 0.2}) for k in range(GRID_DATASETS)]
    x, u, y = (np.stack([q[i] for q in parts]) for i in range(3))
    return x, u, y


def bench_grid(epochs: int, probe_steps: int) -> float:
    full = epochs == GRID_EPOCHS
    _say(f"== 2b. convergence grid: nets {list(GRID_NETS)} x N {list(GRID_N)} x {GRID_DATASETS} datasets "
         f"(friction, sigma 0.2 on v, SA spec, batch {GRID_BATCH}, {GRID_EPOCHS} epochs) ==")
    _say("   grouped: each (net, N) cell's 15 datasets train as ONE ensemble (per-member data, per-member "
         "normalisation and shuffles; every member does exactly epochs * floor(N / B) steps, like a solo run)")
    if full:
        _say(f"   grouped: measured in full ({GRID_EPOCHS} epochs)")
    else:
        _say(f"   grouped: measured for {epochs} of {GRID_EPOCHS} epochs, EXTRAPOLATED x{GRID_EPOCHS / epochs:g} "
             "(time per epoch is constant after the first; --full-grid measures all 200)")
    _say(f"   one-by-one: EXTRAPOLATED from >= {probe_steps} measured steps of one solo run per cell "
         f"(x steps per run x {GRID_DATASETS} datasets)")
    system = get_system("friction")
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    tot = {"grouped fast": 0.0, "one-by-one plain": 0.0, "one-by-one fast": 0.0}
    lagr: dict[tuple[tuple[int, int], int], np.ndarray] = {}
    _say(f"   {'net':>6s} {'N':>6s} {'steps/run':>9s} | {'grouped fast':>12s} | {'1-by-1 plain':>12s} "
         f"{'1-by-1 fast':>12s} (s, whole cell)")
    for hidden in GRID_NETS:
        for n in GRID_N:
            x, u, y = grid_data(system, n)
            bsz = min(GRID_BATCH, n)
            steps_run = GRID_EPOCHS * max(1, n // bsz)
            cfg = TrainConfig.paper(epochs=epochs, batch_size=GRID_BATCH, engine="fast")
            secs, tr, data = _train_group(system, spec, x, u, y, cfg, list(range(GRID_DATASETS)), hidden)
            grouped = secs * GRID_EPOCHS / epochs
            if full:
                lagr[(hidden, n)] = tr.evaluate(data)["lagrangian"]
            solo = {}
            for engine in ("plain", "fast"):
                probe_epochs = max(1, -(-probe_steps // max(1, n // bsz)))
                c = TrainConfig.paper(epochs=probe_epochs, batch_size=GRID_BATCH, engine=engine)
                s, t1, _ = _train_group(system, spec, x[:1], u[:1], y[:1], c, [0], hidden)
                solo[engine] = s / t1.steps * steps_run * GRID_DATASETS
            tot["grouped fast"] += grouped
            tot["one-by-one plain"] += solo["plain"]
            tot["one-by-one fast"] += solo["fast"]
            _say(f"   {str(hidden):>6s} {n:6d} {steps_run:9d} | {grouped:12.2f} | {solo['plain']:12.1f} "
                 f"{solo['fast']:12.1f}")
    _say(f"   total: grouped fast {tot['grouped fast']:.1f} s{'' if full else ' (extrapolated)'}; one-by-one "
         f"plain {tot['one-by-one plain']:.0f} s, one-by-one fast {tot['one-by-one fast']:.0f} s (extrapolated)")
    r = tot["one-by-one plain"] / tot["grouped fast"]
    _say(f"   RATIO one-by-one (plain engine) / grouped (fast engine): {r:.1f}x; one-by-one (fast engine) / "
         f"grouped: {tot['one-by-one fast'] / tot['grouped fast']:.1f}x")
    if full:
        _say("   final training-set Lagrangian, median over the 15 datasets (the paper's Figure: approaches P*):")
        _say("   " + " " * 8 + "".join(f"{n:>9d}" for n in GRID_N))
        for hidden in GRID_NETS:
            _say(f"   {str(hidden):>8s}" + "".join(f"{float(np.median(lagr[(hidden, n)])):9.4f}" for n in GRID_N))
    return r


# ------------------------------------------------------------------------------------------------- 3 ceiling
def matmul_rate(threads: int, size: int = 2048, reps: int = 3) -> float:
    """Best float32 ``torch.mm`` rate in FLOP/s on ``size x size`` matrices with ``threads`` threads."""
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        a, b = torch.randn(size, size), torch.randn(size, size)
        torch.mm(a, b)
        best = min(timed(lambda: torch.mm(a, b)) for _ in range(reps))
    finally:
        torch.set_num_threads(old)
    return 2 * size**3 / best


def bench_ceiling(achieved: dict[str, float]) -> None:
    _say("== 3. arithmetic ceiling: FLOPs per sample vs measured float32 matmul rate ==")
    n_cores = torch.get_num_threads() if torch.get_num_threads() > 1 else max(1, len(_cpus()))
    r1 = matmul_rate(1)
    rn = matmul_rate(n_cores)
    _say(f"   torch.mm 2048x2048 float32: {r1 / 1e9:.1f} GFLOP/s on 1 thread, {rn / 1e9:.1f} GFLOP/s on "
         f"{n_cores} threads")
    for name, sysname, hidden, _, _, _ in THROUGHPUT_CASES:
        system = get_system(sysname)
        per = flops_per_sample(system, hidden)  # forward + backward ~ 3x the forward matmul FLOPs
        fwd = per // 3
        ceil1 = r1 / per
        got = achieved.get(name)
        frac = f"; achieved {got / 1e6:.3f} M samples/s = {100 * got / ceil1:.2f}% of the 1-thread ceiling" \
            if got else ""
        _say(f"   {name}: {per} FLOP/sample (fwd {fwd}) -> ceiling {ceil1 / 1e6:.1f} M samples/s on 1 thread, "
             f"{rn / per / 1e6:.1f} M on {n_cores}{frac}")


def _cpus() -> list[int]:
    import os

    return sorted(os.sched_getaffinity(0))


# ------------------------------------------------------------------------------------------------- main
def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=1, help="intra-op threads for sections 1-2 (default 1)")
    ap.add_argument("--rounds", type=int, default=7, help="interleaved timing rounds in section 1")
    ap.add_argument("--fit-epochs", type=int, default=50,
                    help="epochs per timed fit in section 1 (default 50: a training run's steady state)")
    ap.add_argument("--grid-epochs", type=int, default=10, help="epochs of the grid measured (of 200)")
    ap.add_argument("--full-grid", action="store_true", help="measure the grid's 200 epochs (minutes)")
    ap.add_argument("--profile", action="store_true", help="print a torch.profiler table per throughput case")
    ap.add_argument("--sections", default="1,2,3", help="comma-separated subset of 1, 2, 3")
    args = ap.parse_args(argv)
    logging.getLogger("saml_ros.trainer").setLevel(logging.ERROR)  # short runs leave constraints violated
    torch.set_num_threads(args.threads)
    sections = {s.strip() for s in args.sections.split(",")}
    t0 = time.perf_counter()
    _say(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op thread(s), "
         f"CPU capability {torch.backends.cpu.get_cpu_capability()}")
    achieved: dict[str, float] = {}
    if "1" in sections:
        achieved = bench_throughput(args.rounds, args.profile, args.fit_epochs)
    if "2" in sections:
        bench_seeds(15, 2)
        bench_grid(GRID_EPOCHS if args.full_grid else args.grid_epochs, probe_steps=150)
    if "3" in sections:
        bench_ceiling(achieved)
    _say(f"(whole benchmark: {time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
