"""``layouts``: write the PlotJuggler / Foxglove layouts, or draw their panels from a bag.

    layouts write --out layouts                       # every system, default namespaces /<system>
    layouts write --out my_layouts --namespace /robot1
    layouts write --system-file examples/diff_drive/system.yaml --namespace /dd     # a robot's own topics
    layouts render runs/bag --system quadrotor -o panels.png

Open them with ``ros2 run plotjuggler plotjuggler -l layouts/quadrotor.plotjuggler.xml`` or Foxglove's
*Import layout* (``layouts/quadrotor.foxglove.json``); see docs/launch.md.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from saml_ros.core.systems.registry import SYSTEM_NAMES


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="layouts", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n", 1)[1])
    sub = p.add_subparsers(dest="command", required=True)
    w = sub.add_parser("write", help="write <system>.plotjuggler.xml and <system>.foxglove.json")
    w.add_argument("--out", type=Path, default=Path("layouts"), help="directory (default: layouts)")
    w.add_argument("--namespace", help="namespace of the loop's topics (default: /<system> for each system)")
    w.add_argument("--system-file", type=Path, help="only the layouts of this robot (docs/your_robot.md)")
    r = sub.add_parser("render", help="draw a layout's panels from a recorded bag into a PNG")
    r.add_argument("bag", type=Path)
    which = r.add_mutually_exclusive_group(required=True)
    which.add_argument("--system", choices=SYSTEM_NAMES)
    which.add_argument("--system-file", type=Path, help="a robot described by a system file")
    r.add_argument("--namespace", help="namespace of the loop's topics in the bag (default: /<system>)")
    r.add_argument("-o", "--output", type=Path, required=True, help="PNG to write")
    r.add_argument("--title", help="figure title (default: names the bag)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    systems = SYSTEM_NAMES
    if args.system_file is not None:
        from saml_ros.systems.system_file import SystemFileError
        from saml_ros.user_code import load_system_file

        try:
            systems = (load_system_file(args.system_file).name,)
        except SystemFileError as exc:
            print(f"layouts: {exc}", file=sys.stderr)
            return 2
        if args.command == "render":
            args.system = systems[0]
    if args.command == "write":
        from saml_ros.viewers.layouts import write_layouts

        for path in write_layouts(args.out, args.namespace, systems):
            print(path)
        return 0
    from saml_ros.bags.io import BagError
    from saml_ros.viewers.render import render_layout

    try:
        print(render_layout(args.bag, args.system, args.output, args.namespace, args.title))
    except BagError as exc:
        print(f"layouts: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
