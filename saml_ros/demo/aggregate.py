"""Several demo runs pooled (``./dev demo --aggregate RUN_DIR ...``): issue #10's "what must show" over all of them.

Every run directory holds the ``demo_summary.json`` that ``./dev demo`` wrote. Pooled over the runs' evaluation
starts (each run draws its own: the seeds add ``--seed``), paired per start: the learned models' gain over the base
model on the task metric with its 95 % t CI and the fraction of the oracle's headroom it captures (bootstrap 95 %),
SA vs UA, and the worst cases -- evaluation episodes ending more than 1 m from the pad and the worst learned
episode against the worst base episode over the same starts -- plus the live learned-model episodes of every run.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.demo.landing import FAR, METRICS, TASK_METRIC

#: the file each demo run writes into its run directory
SUMMARY = "demo_summary.json"


def load_runs(dirs: list[Path]) -> list[dict[str, Any]]:
    """The ``demo_summary.json`` of every run directory (a missing one raises FileNotFoundError)."""
    return [json.loads((Path(d) / SUMMARY).read_text()) for d in dirs]


def pool(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per start set and over all sets: every arm's per-start metrics concatenated over the runs (the same starts
    for every arm within a run); runs without an evaluation (no checkpoint) are skipped."""
    sets: dict[str, dict[str, dict[str, list[float]]]] = {}
    for run in runs:
        ev = run.get("evaluation")
        if not ev:
            continue
        arms = ev["arms"]
        for name, s in ev["sets"].items():
            if not all(a in s["per_start"] for a in arms):
                continue
            for target in (name, "all"):
                dst = sets.setdefault(target, {})
                for a in arms:
                    for k, v in s["per_start"][a].items():
                        dst.setdefault(a, {}).setdefault(k, []).extend(float(x) for x in v)
    return sets


def aggregate(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The pooled statistics (see the module docstring)."""
    from saml_ros.demo.evaluation import captured, paired_diff

    sets = pool(runs)
    out: dict[str, Any] = {"runs": len(runs), "sets": {}}
    for name, arms in sets.items():
        if "base" not in arms:
            continue
        res: dict[str, Any] = {"n": len(arms["base"][TASK_METRIC]), "metrics": {}}
        learned = [a for a in arms if a not in ("base", "oracle")]
        for k in METRICS:
            row: dict[str, Any] = {"mean": {a: float(np.nanmean(arms[a][k])) for a in arms}}
            b = np.asarray(arms["base"][k])
            if "oracle" in arms:
                row["headroom"] = paired_diff(b, np.asarray(arms["oracle"][k]))
            for a in learned:
                row[f"gain/{a}"] = paired_diff(b, np.asarray(arms[a][k]))
                if "oracle" in arms:
                    row[f"captured/{a}"] = captured(b, np.asarray(arms[a][k]), np.asarray(arms["oracle"][k]))
            if "SA" in arms and "UA" in arms:
                row["sa_vs_ua"] = paired_diff(np.asarray(arms["UA"][k]), np.asarray(arms["SA"][k]))
            res["metrics"][k] = row
        res["worst"] = {a: float(np.max(arms[a][TASK_METRIC])) for a in arms}
        res["far"] = {a: int(np.sum(np.asarray(arms[a][TASK_METRIC]) > FAR)) for a in arms}
        out["sets"][name] = res
    live = [e for run in runs for e in run.get("bringup", {}).get("episodes", []) if e.get("model_first", 0) > 0]
    live_base = [e for run in runs for e in run.get("bringup", {}).get("episodes", []) if e.get("model_last", 0) == 0]
    out["live"] = {"learned_episodes": len(live), "learned_far": sum(e["error"] > FAR for e in live),
                   "learned_worst": max((e["error"] for e in live), default=math.nan),
                   "base_episodes": len(live_base),
                   "base_worst": max((e["error"] for e in live_base), default=math.nan)}
    out["wall_seconds"] = [float(run.get("wall_seconds", math.nan)) for run in runs]
    return out


def _ci(d: dict[str, float], digits: int = 4) -> str:
    return f"{d['diff']:+.{digits}f} [{d['lo']:+.{digits}f}, {d['hi']:+.{digits}f}]"


def format_aggregate(agg: dict[str, Any]) -> str:
    """A markdown report of :func:`aggregate`."""
    walls = ", ".join(f"{w:.0f}" for w in agg["wall_seconds"])
    lines = [f"# {agg['runs']} demo runs pooled", "", f"wall time per run (s): {walls}", ""]
    for name, s in agg["sets"].items():
        arms = list(s["metrics"][TASK_METRIC]["mean"])
        learned = [a for a in arms if a not in ("base", "oracle")]
        lines += [f"## {name} starts ({s['n']}, paired)", "",
                  "| metric | " + " | ".join(arms) + " | headroom base - oracle | "
                  + " | ".join(f"gain base - {a} | captured ({a})" for a in learned)
                  + (" | UA - SA |" if "SA" in arms and "UA" in arms else " |"),
                  "|---" * (1 + len(arms) + 1 + 2 * len(learned) + ("SA" in arms and "UA" in arms)) + "|"]
        for k, (label, unit) in METRICS.items():
            row = s["metrics"][k]
            cells = [f"{label} ({unit})".replace("|", "\\|")] + [f"{row['mean'][a]:.4f}" for a in arms]
            cells.append(_ci(row["headroom"]) if "headroom" in row else "")
            for a in learned:
                c = row.get(f"captured/{a}", {})
                cells.append(_ci(row[f"gain/{a}"]))
                cap = c.get("capture", math.nan)
                cells.append(f"{100 * cap:.0f}% [{100 * c['lo']:.0f}, {100 * c['hi']:.0f}]"
                             if math.isfinite(cap) else "n/a")
            if "sa_vs_ua" in row:
                cells.append(_ci(row["sa_vs_ua"]))
            lines.append("| " + " | ".join(cells) + " |")
        lines += ["", "worst landing error (m): " + ", ".join(f"{a} {s['worst'][a]:.3f}" for a in arms),
                  f"episodes ending > {FAR:g} m from the pad: " + ", ".join(f"{a} {s['far'][a]}" for a in arms), ""]
    lines += ["## checks (issue #10)", ""] + [f"- {c}" for c in checks(agg)]
    return "\n".join(lines) + "\n"


def checks(agg: dict[str, Any]) -> list[str]:
    """The "what must show" statements on the pooled numbers, each with yes / NO."""
    out = []
    std, every = agg["sets"].get("standard"), agg["sets"].get("all")
    for a in ("SA", "UA"):
        if std is None or f"gain/{a}" not in std["metrics"][TASK_METRIC]:
            continue
        g = std["metrics"][TASK_METRIC][f"gain/{a}"]
        c = std["metrics"][TASK_METRIC][f"captured/{a}"]
        out.append(f"{a} gain over base on the landing error (standard starts, n = {std['n']}): {_ci(g)} m, CI "
                   f"excludes 0: {'yes' if g['lo'] > 0 else 'NO'}; captures {100 * c['capture']:.0f}% "
                   f"[{100 * c['lo']:.0f}, {100 * c['hi']:.0f}] of the oracle's headroom (>= 50%: "
                   f"{'yes' if c['capture'] >= 0.5 else 'NO'})")
    if std is not None and "sa_vs_ua" in std["metrics"][TASK_METRIC]:
        d = std["metrics"][TASK_METRIC]["sa_vs_ua"]
        out.append(f"SA vs UA on the landing error (standard starts): UA - SA = {_ci(d)} m (p = {d['p']:.2g})")
    if every is not None:
        for a in every["worst"]:
            if a in ("base", "oracle"):
                continue
            out.append(f"{a}: {every['far'][a]} of {every['n']} evaluation episodes (standard + aggressive) end "
                       f"> {FAR:g} m from the pad; worst {every['worst'][a]:.3f} m vs base's worst "
                       f"{every['worst']['base']:.3f} m over the same starts (no worse: "
                       f"{'yes' if every['worst'][a] <= every['worst']['base'] else 'NO'})")
    lv = agg["live"]
    out.append(f"live: {lv['learned_far']} of {lv['learned_episodes']} episodes begun on a learned model end > "
               f"{FAR:g} m off (worst {lv['learned_worst']:.3f} m; live episodes flown on f_hat only: worst "
               f"{lv['base_worst']:.3f} m of {lv['base_episodes']})")
    return out


def aggregate_main(argv: list[str]) -> int:
    """``demo --aggregate RUN_DIR [RUN_DIR ...] [--out DIR]``: print the pooled report, write it as md + json."""
    import argparse

    p = argparse.ArgumentParser(prog="demo --aggregate", description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="run directories of ./dev demo")
    p.add_argument("--out", type=Path, help="write demo_aggregate.md / .json here (default: the first run's parent)")
    args = p.parse_args(argv)
    agg = aggregate(load_runs(args.runs))
    text = format_aggregate(agg)
    print(text)
    out = args.out or Path(args.runs[0]).resolve().parent
    out.mkdir(parents=True, exist_ok=True)
    (out / "demo_aggregate.md").write_text(text)
    (out / "demo_aggregate.json").write_text(json.dumps(agg, indent=1, default=float))
    print(f"written: {out / 'demo_aggregate.md'}, {out / 'demo_aggregate.json'}")
    return 0
