"""Run every benchmark (``./dev bench``) or the named ones (``./dev bench train mpc``); options after the names go
to each named benchmark (``./dev bench learner --part training``).

Each benchmark runs in its own process (so one's threads and DDS participants cannot disturb another) and
prints ratios measured within its own run; see docs/performance.md.
"""

from __future__ import annotations

import subprocess
import sys
import time

BENCHES = ("train", "dual", "cooper", "mpc", "sim", "loop_parts", "learner", "closed_loop", "bags", "health", "soak",
           "sweep", "storage", "pairing", "misconfig", "your_robot")


def main(argv: list[str] | None = None) -> int:
    args = list(argv if argv is not None else sys.argv[1:])
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
        rc = subprocess.call([sys.executable, "-m", f"bench.bench_{name}", *options])
        print(f"----- bench_{name}: exit {rc}, {time.perf_counter() - t0:.0f} s", flush=True)
        if rc != 0:
            failed.append(name)
    if failed:
        print(f"bench: failed: {failed}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
