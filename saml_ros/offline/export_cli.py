"""``ros2 run saml_ros export`` / ``./dev export``: write a learned model as ONNX, TorchScript, numpy weights and a
CasADi Function (the weights a parameter vector).

    export runs/dd -o export/dd                      # the run directory's newest checkpoint, every format
    export runs/dd/ckpt-000004.saml -o out --format onnx numpy

Each file is checked against the in-package model on random inputs inside the system's ranges; the largest
difference is printed and stored in ``model.json`` (see saml_ros.export and docs/your_robot.md).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from saml_ros.export import FORMATS, ONNX_EXPORTERS, ExportError


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="export", description="Export a learned model (ONNX, TorchScript, numpy, "
                                                           "CasADi).",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("model", type=Path, help="a checkpoint file or a run directory (its newest checkpoint)")
    p.add_argument("-o", "--out", type=Path, required=True, help="output directory")
    p.add_argument("--format", nargs="+", choices=FORMATS, default=list(FORMATS), help="what to write")
    p.add_argument("--onnx-exporter", choices=ONNX_EXPORTERS, default="torchscript",
                   help="torch's TorchScript-based ONNX exporter, or the torch.export-based one (needs onnxscript)")
    p.add_argument("--member", type=int, default=0, help="ensemble member to export")
    p.add_argument("--check-samples", type=int, default=1000, help="random inputs the export is checked on")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from saml_ros.api import load_model
    from saml_ros.core.model.checkpoint import CheckpointError

    try:
        model = load_model(args.model, member=args.member)
        result = model.export(args.out, args.format, onnx_exporter=args.onnx_exporter,
                              check_samples=args.check_samples)
    except (FileNotFoundError, CheckpointError, ExportError, ValueError) as exc:
        print(f"export: {exc}", file=sys.stderr)
        return 2
    print(f"export: {model.system.name} from {model.path} -> {result.out_dir}")
    for fmt, path in result.files.items():
        print(f"export: {fmt:12s} {path}  (max |export - model| = {result.max_abs_error[fmt]:.3g} on "
              f"{result.n_checked} random inputs)")
    if not result.base_exported:
        print("export: WARNING the base model could not be traced: the ONNX / TorchScript files hold the residual "
              "phi alone (see model.json)")
    if "casadi" in result.files:
        meta = json.loads((result.out_dir / "model.json").read_text())
        if not meta.get("casadi_base_exported"):
            print(f"export: note: model.casadi holds the residual phi alone: {meta.get('casadi_base_export_problem')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
