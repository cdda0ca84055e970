"""Export a learned dynamics model for use outside saml_ros (a C++ / acados / L4CasADi controller, ...).

:func:`export_model` writes into a directory:

* ``model.onnx`` (format ``onnx``): inputs ``x (B, n_x)``, ``u (B, n_u)``; outputs ``y (B, n_y)`` (the full
  prediction f_hat + phi) and ``residual (B, n_y)`` (phi alone), batch size free, in the model's dtype. Written
  with torch's TorchScript-based ONNX exporter (fast, no extra package) or, with ``onnx_exporter="dynamo"``, its
  torch.export-based one (needs ``onnxscript``). Run it with onnxruntime (Python, C, C++).
* ``model.pt`` (format ``torchscript``): the same function, ``y, residual = module(x, u)``; loads in C++ with
  ``torch::jit::load`` and in Python with ``torch.jit.load`` (what L4CasADi takes).
* ``weights.npz`` (format ``numpy``): the residual network's normalisation and weights as plain arrays
  (``in_mean``, ``in_std``, ``out_std``, ``W0``, ``b0``, ``slope0``, ..., see :func:`numpy_residual`) for a
  controller that rebuilds phi itself (acados / CasADi expressions, embedded code).
* ``model.casadi`` + ``theta.npy`` (format ``casadi``): a CasADi Function ``model(x (n_x,), u (n_u,), theta) ->
  (y, residual)`` saved with ``Function.save`` (``casadi.Function.load`` in Python, C++, MATLAB), with the network's
  weights as the *parameter vector* ``theta`` (``theta.npy``; its layout is in ``model.json``,
  :func:`saml_ros.core.mpc.generic.casadi_model.theta_layout`). f_hat is in it where it has a symbolic form (a
  system file's built-in base models and array-namespace forms); otherwise ``y`` is phi alone
  (``"casadi_base_exported": false``). An acados or CasADi controller built on it takes a new checkpoint by
  passing a new ``theta``, without rebuilding or regenerating code. ``model_smooth.casadi`` is the same with a fourth
  input ``eps`` rounding the PReLU kinks (``|h| -> sqrt(h^2 + eps^2)``) for interior point solvers (IPOPT), which do
  not converge on the exact kinks; ``eps = 0`` gives the exact network.
* ``model.json``: fields, units, dt, the architecture, the base model's description, the files and the check.

If the base model cannot be traced (a user's f_hat with Python control flow on values), the ONNX and TorchScript
files hold the residual alone (``y`` then equals ``residual``) and ``model.json`` says so (``"base_exported": false``).

Every export is **checked** against the in-package model on random inputs inside the system's input ranges
(:func:`check_export`): the largest absolute difference per format goes into ``model.json``, and an export that
differs by more than the tolerance (``1e-9`` relative for float64 models, ``1e-4`` for float32) raises
:class:`ExportError`.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from saml_ros.core.errors import SamlError
from saml_ros.core.model.network import DynamicsModel, dense_input_layer

FORMATS: tuple[str, ...] = ("onnx", "torchscript", "numpy", "casadi")
ONNX_EXPORTERS: tuple[str, ...] = ("torchscript", "dynamo")
EXPORT_FORMAT = "saml_ros.export"
EXPORT_VERSION = 1


class ExportError(SamlError, RuntimeError):
    """An export could not be written, or does not reproduce the model."""


class _Exported(nn.Module):
    """``(x, u) -> (f_hat + phi, phi)`` of one ensemble member, as a plain module to trace."""

    def __init__(self, model: DynamicsModel, member: int, with_base: bool) -> None:
        super().__init__()
        self.model = model.member(member) if model.n_models > 1 else model
        self.with_base = with_base

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        phi = self.model.correction(x, u)[0]
        if self.model.kind == "full" or not self.with_base:
            return phi, phi
        return phi + self.model.base(x, u), phi


@dataclass
class ExportResult:
    """What :func:`export_model` wrote.

    Attributes:
        out_dir: the directory.
        files: ``{format: path}``.
        max_abs_error: ``{format: largest |export - model|}`` over the check inputs (full prediction).
        base_exported: whether the ONNX / TorchScript files include the base model.
        n_checked: inputs the check used.
    """

    out_dir: Path
    files: dict[str, Path] = field(default_factory=dict)
    max_abs_error: dict[str, float] = field(default_factory=dict)
    base_exported: bool = True
    n_checked: int = 0


def numpy_residual(weights: dict[str, np.ndarray], x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """phi(x, u) from ``weights.npz`` in plain numpy: ``(B, n_x), (B, n_u) -> (B, n_y)``.

    ``z = ([x, u] - in_mean) / in_std``; per hidden layer ``h = z @ W_l + b_l`` then PReLU with slope ``slope_l``
    (``h if h >= 0 else slope_l * h``); the last layer is linear; the output is multiplied by ``out_std``.
    """
    z = (np.concatenate([x, u], axis=-1) - weights["in_mean"]) / weights["in_std"]
    n = int(weights["n_layers"])
    for i in range(n):
        z = z @ weights[f"W{i}"] + weights[f"b{i}"]
        if i < n - 1:
            z = np.where(z >= 0, z, weights[f"slope{i}"] * z)
    return np.asarray(z * weights["out_std"])


def numpy_weights(model: DynamicsModel, member: int = 0) -> dict[str, np.ndarray]:
    """The arrays :func:`numpy_residual` takes, for ensemble member ``member`` (model dtype)."""
    net = model.net
    dt = model.in_mean.numpy().dtype
    mean, std, w0 = (a.astype(dt) for a in dense_input_layer(model, member))  # every [x, u] field, zero rows unseen
    out: dict[str, np.ndarray] = {
        "in_mean": mean,
        "in_std": std,
        "out_std": model.out_std[member, 0].detach().numpy().copy(),
        "n_layers": np.array(len(net.weights)),
    }
    for i, (w, b) in enumerate(zip(net.weights, net.biases, strict=True)):
        out[f"W{i}"] = w0 if i == 0 else w[member].detach().numpy().copy()
        out[f"b{i}"] = b[member, 0].detach().numpy().copy()
    for i, s in enumerate(net.slopes):
        out[f"slope{i}"] = s[member].detach().numpy().reshape(()).copy()
    return out


def export_model(model: DynamicsModel, out_dir: str | Path, formats: Sequence[str] = FORMATS, *,
                 member: int = 0, onnx_exporter: str = "torchscript", check_samples: int = 1000, seed: int = 0,
                 extra_meta: dict[str, Any] | None = None) -> ExportResult:
    """Write ``model`` (member ``member``) in ``formats`` into ``out_dir`` and check each file (module docstring).
    One function on purpose (longer than 80 lines): each format's export is a few lines followed by the same
    reproduction check on shared probe inputs.

    Raises:
        ExportError: an unknown format / exporter, a missing package (onnx, onnxruntime, onnxscript), or an export
            that does not reproduce the model.
    """
    unknown = sorted(set(formats) - set(FORMATS))
    if unknown or not formats:
        raise ExportError(f"unknown export format(s) {unknown or formats}; valid: {list(FORMATS)}")
    if onnx_exporter not in ONNX_EXPORTERS:
        raise ExportError(f"unknown ONNX exporter {onnx_exporter!r}; valid: {list(ONNX_EXPORTERS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    system = model.system
    dtype = model.in_mean.dtype
    x, u = _check_inputs(model, check_samples, seed)
    with torch.no_grad():
        want_y = model(x, u)[member].numpy()
        want_phi = model.correction(x, u)[member].numpy()
    result = ExportResult(out, n_checked=len(x))
    module = _Exported(model, member, with_base=True)
    base_problem = ""
    if any(f in formats for f in ("onnx", "torchscript")):
        try:
            traced = _trace(module, x[:4], u[:4])
            with torch.no_grad():
                got = traced(x, u)[0].numpy()
            if not np.allclose(got, want_y, rtol=_tol(dtype), atol=_tol(dtype)):
                raise ExportError("the traced base model differs from the model")
        except Exception as exc:  # noqa: BLE001 - a base model that does not trace: export phi alone
            base_problem = f"{type(exc).__name__}: {exc}"
            module = _Exported(model, member, with_base=False)
            result.base_exported = model.kind == "full"
    ref = {"y": want_y if result.base_exported else want_phi, "residual": want_phi}

    if "torchscript" in formats:
        path = out / "model.pt"
        _trace(module, x[:4], u[:4]).save(str(path))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # torch 2.13 deprecates TorchScript for torch.export
            loaded = torch.jit.load(str(path))
        with torch.no_grad():
            y, phi = (t.numpy() for t in loaded(x, u))
        result.files["torchscript"] = path
        result.max_abs_error["torchscript"] = _compare("torchscript", y, phi, ref, dtype)
    if "onnx" in formats:
        path = out / "model.onnx"
        _export_onnx(module, x[:4], u[:4], path, onnx_exporter)
        y, phi = _run_onnx(path, x.numpy(), u.numpy())
        result.files["onnx"] = path
        result.max_abs_error["onnx"] = _compare("onnx", y, phi, ref, dtype)
    if "numpy" in formats:
        path = out / "weights.npz"
        weights = numpy_weights(model, member)
        np.savez(path, **weights)  # type: ignore[arg-type]
        with np.load(path, allow_pickle=False) as f:
            phi = numpy_residual({k: f[k] for k in f.files}, x.numpy(), u.numpy())
        result.files["numpy"] = path
        result.max_abs_error["numpy"] = _compare("numpy", None, phi, ref, dtype)

    casadi_meta: dict[str, Any] = {}
    if "casadi" in formats:
        casadi_meta = _export_casadi(model, member, out, x.numpy(), u.numpy(), want_y, want_phi, dtype, result)

    meta = {
        "format": EXPORT_FORMAT, "version": EXPORT_VERSION, "system": system.name, "dt": float(system.dt),
        "state": [[f.name, f.unit] for f in system.state.fields],
        "control": [[f.name, f.unit] for f in system.control.fields],
        "target": [[f.name, f.unit] for f in system.target.fields],
        "schema_hash": system.schema_hash(), "architecture": model.architecture(), "member": member,
        "dtype": str(dtype).removeprefix("torch."),
        "base_model": _base_description(system), "base_exported": result.base_exported,
        "base_export_problem": base_problem,
        "files": {k: v.name for k, v in result.files.items()},
        "inputs": {"x": f"(B, {system.state.size})", "u": f"(B, {system.control.size})"},
        "outputs": {"y": "f_hat(x, u) + phi(x, u)" if result.base_exported else "phi(x, u) (base not exported)",
                    "residual": "phi(x, u)"},
        "check": {"n": result.n_checked, "max_abs_error": result.max_abs_error},
        **casadi_meta,
        **(extra_meta or {}),
    }
    (out / "model.json").write_text(json.dumps(meta, indent=2))
    return result


def _export_casadi(model: DynamicsModel, member: int, out: Path, x: np.ndarray, u: np.ndarray, want_y: np.ndarray,
                   want_phi: np.ndarray, dtype: torch.dtype, result: ExportResult) -> dict[str, Any]:
    """Write ``model.casadi`` and ``theta.npy`` (module docstring), check them, return their ``model.json`` part."""
    try:
        import casadi as ca

        from saml_ros.core.mpc.generic.casadi_model import export_function, theta_layout
    except ImportError as exc:
        raise ExportError(f"the CasADi export needs casadi (pip install casadi): {exc}") from None
    fn, theta, base_ok, why = export_function(model, member)
    path = out / "model.casadi"
    fn.save(str(path))
    export_function(model, member, smooth=True)[0].save(str(out / "model_smooth.casadi"))
    np.save(out / "theta.npy", theta)
    loaded = ca.Function.load(str(path))
    y, phi = (np.asarray(v).T for v in loaded.map(len(x))(x.T, u.T, np.load(out / "theta.npy")))
    result.files["casadi"] = path
    result.max_abs_error["casadi"] = _compare("casadi", y if base_ok else None, phi,
                                              {"y": want_y, "residual": want_phi}, dtype)
    smooth = ca.Function.load(str(out / "model_smooth.casadi"))
    ys, phis = (np.asarray(v).T for v in smooth.map(len(x))(x.T, u.T, theta, 0.0))
    _compare("casadi (model_smooth, eps = 0)", ys if base_ok else None, phis, {"y": want_y, "residual": want_phi},
             dtype)
    system = model.system
    layout = theta_layout(system.state.size + system.control.size, model.hidden, system.state.size)
    return {"casadi_base_exported": base_ok, "casadi_base_export_problem": why,
            "casadi": {"function": path.name, "smooth_function": "model_smooth.casadi", "theta": "theta.npy",
                       "inputs": ["x", "u", "theta"], "smooth_inputs": ["x", "u", "theta", "eps"],
                       "outputs": ["y", "residual"], "theta_size": int(theta.size),
                       "theta_layout": [[name, list(shape)] for name, shape in layout],
                       "prelu": "0.5 (1 + a) h + 0.5 (1 - a) |h|"}}


def _check_inputs(model: DynamicsModel, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    system = model.system
    rng = np.random.default_rng(seed)
    try:
        x, u = system.sample_inputs(n, rng)
    except Exception:  # noqa: BLE001 - a system without a sampler: the model's own input statistics
        mean, std, _ = dense_input_layer(model, 0)
        z = rng.normal(mean, std, (n, len(mean)))
        x, u = z[:, : system.state.size], z[:, system.state.size:]
    dt = model.in_mean.dtype
    return torch.as_tensor(np.asarray(x), dtype=dt), torch.as_tensor(np.asarray(u), dtype=dt)


def _tol(dtype: torch.dtype) -> float:
    return 1e-9 if dtype == torch.float64 else 1e-4


def _compare(fmt: str, y: np.ndarray | None, phi: np.ndarray, ref: dict[str, np.ndarray], dtype: torch.dtype) -> float:
    errs = [float(np.max(np.abs(phi - ref["residual"])))]
    scale = [float(np.max(np.abs(ref["residual"])))]
    if y is not None:
        errs.append(float(np.max(np.abs(y - ref["y"]))))
        scale.append(float(np.max(np.abs(ref["y"]))))
    tol = _tol(dtype)
    for e, s in zip(errs, scale, strict=True):
        if not e <= tol * max(1.0, s):
            raise ExportError(f"the {fmt} export differs from the model by {e:.3g} (tolerance {tol * max(1.0, s):.3g})")
    return max(errs)


def _trace(module: nn.Module, x: torch.Tensor, u: torch.Tensor) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.trace(module, (x, u), check_trace=False)


def _export_onnx(module: nn.Module, x: torch.Tensor, u: torch.Tensor, path: Path, exporter: str) -> None:
    try:
        import onnx  # noqa: F401 - the exporters need it
    except ImportError:
        raise ExportError("ONNX export needs the 'onnx' package (pip install onnx onnxruntime)") from None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if exporter == "dynamo":
            try:
                import onnxscript  # noqa: F401
            except ImportError:
                raise ExportError("the dynamo ONNX exporter needs 'onnxscript' (pip install onnxscript)") from None
            batch = torch.export.Dim("batch")
            prog = torch.onnx.export(module, (x, u), dynamo=True, input_names=["x", "u"],
                                     output_names=["y", "residual"], dynamic_shapes=({0: batch}, {0: batch}))
            assert prog is not None
            prog.save(str(path))
        else:
            torch.onnx.export(module, (x, u), str(path), dynamo=False, input_names=["x", "u"],
                              output_names=["y", "residual"],
                              dynamic_axes={"x": {0: "batch"}, "u": {0: "batch"}, "y": {0: "batch"},
                                            "residual": {0: "batch"}})


def _run_onnx(path: Path, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    try:
        import onnxruntime
    except ImportError:
        raise ExportError("checking an ONNX export needs 'onnxruntime' (pip install onnxruntime)") from None
    sess = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    y, phi = sess.run(["y", "residual"], {"x": x, "u": u})
    return np.asarray(y), np.asarray(phi)


def _base_description(system: Any) -> Any:
    params = getattr(system, "params", None)
    if callable(params):
        p = params()
        if "definition" in p:
            return p["definition"].get("base_model")
        return {"system": system.name, "params": p}
    return {"system": system.name}
