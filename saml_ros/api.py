"""Use a learned model from your own Python code: ``load_model(path).predict(x, u)``.

    from saml_ros.api import load_model

    model = load_model("runs/dd")                 # a run directory (its newest checkpoint) or a .saml file
    model.state_fields, model.units               # ('x', 'y', 'yaw', 'v', 'w'), {'x': 'm', ...}
    y = model.predict(x, u)                       # x (B, n_x), u (B, n_u) float arrays -> (B, n_y); or one (n,)
    y = model.predict({"x": xs, "y": ys, ...}, {"v_cmd": vs, "w_cmd": ws})   # by field name -> dict by name
    model.export("export/dd")                     # ONNX + TorchScript + numpy weights, checked (core.export)

Values are in the units of the system's fields (SI, REP 103). Nothing here imports ROS; loading never runs code
from the checkpoint (a robot from a system file is rebuilt from the definition stored in it, and only a base
model *named* there, a built-in or an installed function, is imported).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from saml_ros.core.model.checkpoint import CheckpointStore, read_checkpoint
from saml_ros.core.model.io import LoadedModel, model_from_payload
from saml_ros.export import FORMATS, ExportResult, export_model


class Model:
    """A learned dynamics model with named, unit-carrying inputs and outputs (see the module docstring)."""

    def __init__(self, loaded: LoadedModel, member: int = 0) -> None:
        self.loaded = loaded
        self.member = member
        self.system = loaded.system
        self.dt = float(self.system.dt)
        self.state_fields = tuple(self.system.state.names)
        self.control_fields = tuple(self.system.control.names)
        self.target_fields = tuple(self.system.target.names)
        self.units = {f.name: f.unit for lay in (self.system.state, self.system.control, self.system.target)
                      for f in lay.fields}
        self._dtype = loaded.model.in_mean.dtype

    @property
    def path(self) -> Path | None:
        return self.loaded.path

    def __repr__(self) -> str:
        fields = ", ".join(f"{n} [{self.units[n]}]" for n in self.state_fields)
        return f"Model({self.system.name!r}, state: {fields}; dt = {self.dt} s; {self.loaded.path})"

    def _as_array(self, v: Any, names: Sequence[str], what: str) -> tuple[np.ndarray, bool, bool]:
        """``(B, n)`` float64, whether the input was a single vector, whether it was a dict."""
        if isinstance(v, Mapping):
            missing = [n for n in names if n not in v]
            extra = sorted(set(v) - set(names))
            if missing or extra:
                raise ValueError(f"{what}: missing fields {missing}, unknown fields {extra}; expected {list(names)}")
            cols = [np.asarray(v[n], dtype=np.float64) for n in names]
            single = all(c.ndim == 0 for c in cols)
            return np.stack([np.atleast_1d(c) for c in cols], axis=-1), single, True
        arr = np.asarray(v, dtype=np.float64)
        single = arr.ndim == 1
        arr = np.atleast_2d(arr)
        if arr.ndim != 2 or arr.shape[1] != len(names):
            raise ValueError(f"{what}: expected shape (B, {len(names)}) or ({len(names)},) for fields {list(names)}, "
                             f"got {np.shape(v)}")
        return arr, single, False

    def _run(self, x: Any, u: Any, which: str) -> Any:
        xa, single, as_dict = self._as_array(x, self.state_fields, "x")
        ua, _, _ = self._as_array(u, self.control_fields, "u")
        if len(xa) != len(ua):
            raise ValueError(f"x has {len(xa)} rows but u has {len(ua)}")
        m = self.loaded.model
        with torch.no_grad():
            xt = torch.as_tensor(xa, dtype=self._dtype)
            ut = torch.as_tensor(ua, dtype=self._dtype)
            if which == "base":
                y = m.base(xt, ut)
            elif which == "residual":
                y = m.correction(xt, ut)[self.member]
            else:
                y = m(xt, ut)[self.member]
        out = y.double().numpy()
        if as_dict:
            return {n: (out[0, i] if single else out[:, i]) for i, n in enumerate(self.target_fields)}
        return out[0] if single else out

    def predict(self, x: Any, u: Any) -> Any:
        """The model's prediction of the target (the next state): f_hat(x, u) + phi(x, u)."""
        return self._run(x, u, "full")

    def residual(self, x: Any, u: Any) -> Any:
        """phi(x, u) alone (what the network learned on top of the base model)."""
        return self._run(x, u, "residual")

    def base(self, x: Any, u: Any) -> Any:
        """f_hat(x, u) alone (the base model; zeros for a ``full`` model)."""
        return self._run(x, u, "base")

    def export(self, out_dir: str | Path, formats: Sequence[str] = FORMATS, **kwargs: Any) -> ExportResult:
        """Write ONNX / TorchScript / numpy files and check them (see :func:`saml_ros.export.export_model`)."""
        return export_model(self.loaded.model, out_dir, formats, member=self.member,
                            extra_meta={"checkpoint": str(self.loaded.path), "version": self.loaded.version},
                            **kwargs)


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint file, or the newest checkpoint of a run directory; ``FileNotFoundError`` otherwise."""
    p = Path(path)
    if p.is_dir():
        latest = CheckpointStore(p).latest()
        if latest is None:
            raise FileNotFoundError(f"{p}: no checkpoint in this run directory")
        return latest[0]
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such checkpoint or run directory")
    return p


def load_model(path: str | Path, member: int = 0) -> Model:
    """Load a checkpoint (or a run directory's newest) as a :class:`Model` (ensemble member ``member``)."""
    ckpt = resolve_checkpoint(path)
    expect = None
    arrays, meta = read_checkpoint(ckpt)
    definition = (meta.get("system_params") or {}).get("definition") if isinstance(meta, dict) else None
    base = (definition or {}).get("base_model") or {}
    if definition and (base.get("function") or base.get("entry_point")):  # a robot whose base model is user code: import it here
        from saml_ros.user_code import system_from_definition

        expect = system_from_definition(definition)
    loaded = model_from_payload(arrays, meta, expect, ckpt)
    if not 0 <= member < loaded.model.n_models:
        raise ValueError(f"member {member} outside the ensemble of {loaded.model.n_models}")
    return Model(loaded, member)


__all__ = ["Model", "load_model", "resolve_checkpoint"]
