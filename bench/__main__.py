"""Run every benchmark (``./dev bench``) or the named ones (``./dev bench train mpc``); options after the names go
to each named benchmark (``./dev bench learner --part training``).

Each benchmark runs in its own process (so one's threads and DDS participants cannot disturb another) and
prints ratios measured within its own run; see docs/performance.md.

``--results DIR`` (before the names' options: ``./dev bench --results docs/results train``) also writes each
benchmark's output to ``DIR/bench_<name>.md``, headed by the command that rewrites it, the commit, the date and
the load average before and after (the benchmarks' numbers depend on the machine and its load).
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

BENCHES = ("train", "dual", "cooper", "mpc", "generic_mpc", "sim", "loop_parts", "learner", "closed_loop", "bags",
           "health", "soak", "sweep", "storage", "pairing", "misconfig", "your_robot")


def _commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
                             cwd=Path(__file__).resolve().parent)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, cwd=Path(__file__).resolve().parent).stdout.strip()
        return out.stdout.strip() + (" (with uncommitted changes)" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _load() -> str:
    try:
        return " ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def write_result(directory: Path, name: str, options: list[str], output: str, rc: int, seconds: float,
                 load_before: str, commit: str) -> Path:
    """``directory/bench_<name>.md``: the command that rewrites it, where and when it ran, then the output."""
    directory.mkdir(parents=True, exist_ok=True)
    command = " ".join(["./dev bench --results", str(directory), name, *options])
    stamp = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    text = (f"# bench_{name}: latest result\n\n"
            f"Written by `{command}` (rerun it to replace this file).\n\n"
            f"- commit {commit}, {stamp}, exit status {rc}, {seconds:.0f} s\n"
            f"- machine: {platform.machine()}, {os.cpu_count()} CPUs, {platform.python_version()}; load average "
            f"(1, 5, 15 min) {load_before} before, {_load()} after\n\n"
            f"```\n{output.rstrip()}\n```\n")
    path = directory / f"bench_{name}.md"
    path.write_text(text, encoding="utf-8")
    return path


def _run(name: str, options: list[str], results: Path | None) -> int:
    """Run one benchmark in its own process; with ``results``, tee its output into its result file."""
    cmd = [sys.executable, "-m", f"bench.bench_{name}", *options]
    if results is None:
        return subprocess.call(cmd)
    t0, load_before = time.perf_counter(), _load()
    lines = []
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            sys.stdout.write(line)
            sys.stdout.flush()
            lines.append(line)
        rc = proc.wait()
    path = write_result(results, name, options, "".join(lines), rc, time.perf_counter() - t0, load_before, _commit())
    print(f"bench: wrote {path}", flush=True)
    return rc


def main(argv: list[str] | None = None) -> int:
    args = list(argv if argv is not None else sys.argv[1:])
    results: Path | None = None
    if args[:1] == ["--results"]:
        if len(args) < 2:
            print("bench: --results needs a directory", file=sys.stderr)
            return 2
        results, args = Path(args[1]), args[2:]
    first_opt = next((i for i, a in enumerate(args) if a.startswith("-")), len(args))
    names, options = args[:first_opt] or list(BENCHES), args[first_opt:]
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        print(f"bench: unknown benchmark(s) {unknown}; choose from {list(BENCHES)}", file=sys.stderr)
        return 2
    failed = []
    for name in names:
        print(f"\n===== bench_{name} =====", flush=True)
        t0 = time.perf_counter()
        rc = _run(name, options, results)
        print(f"----- bench_{name}: exit {rc}, {time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(name)
    if failed:
        print(f"bench: failed: {failed}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
