"""Sufficiently Accurate problem specs: objective and constraints as data.

A spec is a plain dict (usually loaded from YAML) that is validated against a system's layouts and compiled
into a :class:`ProblemSpec`. Nothing in a spec is ever evaluated as code. The format is documented in
``docs/architecture.md`` (section "Problem spec") and ``docs/spec.md``.

Shapes used below: ``B`` transitions, optionally preceded by ``E`` ensemble members. ``x`` is
``(..., B, n_x)``, ``u`` ``(..., B, n_u)``, ``y`` (observed target) and ``pred`` ``(..., B, n_y)``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from saml_ros.core.errors import SamlError
from saml_ros.core.layout import VectorLayout

if TYPE_CHECKING:
    import torch

LOSS_TYPES = ("l2", "squared_l2", "l1", "huber", "normalized")
MEAN_TYPES = ("conditional", "unconditional")
SOURCES = {"x": "state", "u": "control", "next": "target"}


class SpecError(SamlError, ValueError):
    """A spec that cannot be compiled; the message names the offending path and field."""


# --------------------------------------------------------------------------------------------- regions
class Region:
    """A compiled predicate over (x_t, u_t, y) returning a boolean mask of shape ``(..., B)``."""

    def mask(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError


@dataclass(frozen=True)
class _FieldRef:
    source: str  # "x" | "u" | "next"
    index: int

    def take(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        src = x if self.source == "x" else u if self.source == "u" else y
        return src[..., self.index]


class _Box(Region):
    def __init__(self, bounds: list[tuple[_FieldRef, float, float]]) -> None:
        self.bounds = bounds

    def mask(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        import torch

        m = torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device)
        for ref, lo, hi in self.bounds:
            v = ref.take(x, u, y)
            m = m & (v >= lo) & (v <= hi)
        return m


class _Norm(Region):
    def __init__(self, refs: list[_FieldRef], ord_: float, lo: float, hi: float) -> None:
        self.refs, self.ord, self.lo, self.hi = refs, ord_, lo, hi

    def mask(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        import torch

        v = torch.stack([r.take(x, u, y) for r in self.refs], dim=-1)
        n = torch.linalg.vector_norm(v, ord=self.ord, dim=-1)
        return (n >= self.lo) & (n <= self.hi)


class _Not(Region):
    def __init__(self, inner: Region) -> None:
        self.inner = inner

    def mask(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return ~self.inner.mask(x, u, y)


class _AllOf(Region):
    def __init__(self, parts: list[Region]) -> None:
        self.parts = parts

    def mask(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        m = self.parts[0].mask(x, u, y)
        for p in self.parts[1:]:
            m = m & p.mask(x, u, y)
        return m


class _AnyOf(_AllOf):
    def mask(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        m = self.parts[0].mask(x, u, y)
        for p in self.parts[1:]:
            m = m | p.mask(x, u, y)
        return m


class _Everything(Region):
    def mask(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        import torch

        return torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device)


# --------------------------------------------------------------------------------------------- terms
@dataclass(frozen=True)
class Term:
    """The objective or one constraint.

    Attributes:
        name: identifier used in telemetry (``"objective"`` for the objective).
        loss: one of :data:`LOSS_TYPES`.
        fields: indices into the target vector the error is taken over.
        region: compiled predicate; ``None`` means every transition.
        mean: ``"conditional"`` (E[l | region]) or ``"unconditional"`` (E[l * I_region]).
        eps: constraint bound (``0.0`` for the objective).
        huber_delta: transition point of the Huber loss.
    """

    name: str
    loss: str
    fields: tuple[int, ...]
    region: Region | None
    mean: str
    eps: float = 0.0
    huber_delta: float = 1.0

    def per_sample(self, pred: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Per-transition loss ``(..., B)`` of predictions ``pred`` against observed targets ``y``."""
        import torch

        idx = list(self.fields)
        e = pred[..., idx] - y[..., idx]
        if self.loss == "l2":
            return torch.linalg.vector_norm(e, dim=-1)
        if self.loss == "squared_l2":
            return (e * e).sum(-1)
        if self.loss == "l1":
            return e.abs().sum(-1)
        if self.loss == "huber":
            a = e.abs()
            d = self.huber_delta
            return torch.where(a <= d, 0.5 * e * e, d * (a - 0.5 * d)).sum(-1)
        # normalized: ||e|| / ||y||; the clamp only guards samples outside the term's region
        ny = torch.linalg.vector_norm(y[..., idx], dim=-1).clamp_min(1e-9)
        return torch.linalg.vector_norm(e, dim=-1) / ny

    def mask(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor | None:
        return None if self.region is None else self.region.mask(x, u, y)

    def estimate(self, loss: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """Minibatch estimate ``(...)`` of E[l I] (unconditional) or E[l | I] (conditional), minus eps."""
        import torch

        if mask is None:
            return loss.mean(-1) - self.eps
        m = mask.to(loss.dtype)
        if self.mean == "unconditional":
            return (loss * m).mean(-1) - self.eps
        count = m.sum(-1)
        val = (loss * m).sum(-1) / count.clamp_min(1.0)
        # a minibatch with no sample in the region says nothing about the constraint
        return torch.where(count > 0, val - self.eps, torch.zeros_like(val))


@dataclass
class SpecValues:
    """Minibatch (or dataset) values of a spec.

    Attributes:
        objective: ``(...)`` objective estimate.
        constraints: ``(..., K)`` constraint estimates g_k (<= 0 means satisfied).
        region_fraction: ``(..., K)`` fraction of samples inside each constraint's region.
    """

    objective: torch.Tensor
    constraints: torch.Tensor
    region_fraction: torch.Tensor

    def lagrangian(self, lam: torch.Tensor) -> torch.Tensor:
        """L = objective + sum_k lam_k g_k, with ``lam`` of shape ``(..., K)``."""
        return self.objective + (lam * self.constraints).sum(-1)


class ProblemSpec:
    """A compiled, validated Sufficiently Accurate problem for one system's layouts."""

    def __init__(
        self,
        raw: dict[str, Any],
        objective: Term,
        constraints: list[Term],
        state: VectorLayout,
        control: VectorLayout,
        target: VectorLayout,
    ) -> None:
        self.raw = raw
        self.objective = objective
        self.constraints = constraints
        self.state, self.control, self.target = state, control, target

    # --------------------------------------------------------------------------- construction
    @classmethod
    def from_dict(
        cls, raw: Mapping[str, Any], state: VectorLayout, control: VectorLayout, target: VectorLayout
    ) -> ProblemSpec:
        """Validate and compile ``raw``; raises :class:`SpecError` naming the bad path/field."""
        if not isinstance(raw, Mapping):
            raise SpecError(f"spec: expected a mapping, got {type(raw).__name__}")
        spec_raw: dict[str, Any] = copy.deepcopy(dict(raw))
        raw = spec_raw
        c = _Compiler(state, control, target)
        c.check_keys(raw, "spec", {"name", "description", "objective", "constraints"})
        if "objective" not in raw:
            raise SpecError("spec: missing 'objective'")
        objective = c.term(raw["objective"], "objective", is_constraint=False)
        cons_raw = raw.get("constraints") or []
        if not isinstance(cons_raw, list):
            raise SpecError("spec.constraints: expected a list")
        constraints = [c.term(t, f"constraints[{i}]", is_constraint=True) for i, t in enumerate(cons_raw)]
        names = [t.name for t in constraints]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise SpecError(f"spec.constraints: duplicate constraint names {dup}")
        spec_raw.setdefault("name", "unnamed")
        return cls(spec_raw, objective, constraints, state, control, target)

    @classmethod
    def for_system(cls, raw: Mapping[str, Any], system: Any) -> ProblemSpec:
        """Compile ``raw`` against a :class:`~saml_ros.core.dynamics.system.System`'s layouts."""
        return cls.from_dict(raw, system.state, system.control, system.target)

    @classmethod
    def from_yaml(cls, path: str | Path, system: Any) -> ProblemSpec:
        import yaml

        with open(path) as f:
            try:
                raw = yaml.safe_load(f)
            except yaml.YAMLError as exc:
                raise SpecError(f"{path}: not valid YAML: {exc}") from exc
        try:
            return cls.for_system(raw, system)
        except SpecError as exc:
            raise SpecError(f"{path}: {exc}") from exc

    def to_dict(self) -> dict[str, Any]:
        """The spec as given (JSON/YAML-serialisable); compiling it again gives the same problem."""
        return copy.deepcopy(self.raw)

    def uniform(self) -> ProblemSpec:
        """The Uniformly Accurate baseline: same objective, no constraints."""
        raw = self.to_dict()
        raw["constraints"] = []
        raw["name"] = f"{raw.get('name', 'spec')}_uniform"
        return ProblemSpec.from_dict(raw, self.state, self.control, self.target)

    # --------------------------------------------------------------------------- evaluation
    @property
    def constraint_names(self) -> list[str]:
        return [t.name for t in self.constraints]

    @property
    def n_constraints(self) -> int:
        return len(self.constraints)

    def evaluate(
        self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor, pred: torch.Tensor
    ) -> SpecValues:
        """Objective and constraint estimates of ``pred`` against ``y`` on one batch.

        ``x, u, y`` may lack the leading ensemble dimension of ``pred`` (broadcast).
        """
        masks = self.masks(x, u, y)
        return self.evaluate_with_masks(y, pred, masks)

    def masks(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> list[torch.Tensor | None]:
        """Region masks of the objective followed by each constraint (``None`` = everything)."""
        return [t.mask(x, u, y) for t in (self.objective, *self.constraints)]

    def evaluate_with_masks(
        self, y: torch.Tensor, pred: torch.Tensor, masks: Sequence[torch.Tensor | None]
    ) -> SpecValues:
        import torch

        obj = self.objective.estimate(self.objective.per_sample(pred, y), masks[0])
        lead = obj.shape
        if not self.constraints:
            empty = obj.new_zeros((*lead, 0))
            return SpecValues(obj, empty, empty)
        gs, fr = [], []
        for t, m in zip(self.constraints, masks[1:]):
            gs.append(t.estimate(t.per_sample(pred, y), m))
            frac = obj.new_ones(lead) if m is None else m.to(obj.dtype).mean(-1).expand(lead)
            fr.append(frac)
        return SpecValues(obj, torch.stack(gs, -1), torch.stack(fr, -1))

    def region_errors(
        self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor, pred: torch.Tensor
    ) -> dict[str, dict[str, torch.Tensor]]:
        """Mean per-sample loss of each constraint inside and outside its region, and overall.

        Returns ``{constraint name: {"in": (...), "out": (...), "all": (...), "n_in": (...), "n_out": (...)}}``
        where ``...`` is the leading (ensemble) shape of ``pred``; a mean over no samples is NaN.
        """
        import torch

        out: dict[str, dict[str, torch.Tensor]] = {}
        for t, m in zip(self.constraints, self.masks(x, u, y)[1:]):
            loss = t.per_sample(pred, y).double()
            mm = torch.ones_like(loss) if m is None else m.double().expand_as(loss)
            n_in, n_out = mm.sum(-1), (1 - mm).sum(-1)
            nan = torch.full_like(n_in, math.nan)
            out[t.name] = {
                "in": torch.where(n_in > 0, (loss * mm).sum(-1) / n_in.clamp_min(1), nan),
                "out": torch.where(n_out > 0, (loss * (1 - mm)).sum(-1) / n_out.clamp_min(1), nan),
                "all": loss.mean(-1),
                "n_in": n_in,
                "n_out": n_out,
            }
        return out

    def describe(self) -> str:
        """A short human-readable summary, e.g. for logs and plots."""
        parts = [f"min {self.objective.loss} ({self.objective.mean})"]
        for t in self.constraints:
            parts.append(f"s.t. {t.name}: {t.mean} {t.loss} <= {t.eps:g}")
        return "; ".join(parts)


# --------------------------------------------------------------------------------------------- compiler
class _Compiler:
    def __init__(self, state: VectorLayout, control: VectorLayout, target: VectorLayout) -> None:
        self.layouts = {"x": state, "u": control, "next": target}

    @staticmethod
    def check_keys(d: Any, path: str, allowed: set[str]) -> None:
        if not isinstance(d, Mapping):
            raise SpecError(f"{path}: expected a mapping, got {type(d).__name__}")
        extra = sorted(set(d) - allowed)
        if extra:
            raise SpecError(f"{path}: unknown key(s) {extra}; allowed: {sorted(allowed)}")

    @staticmethod
    def number(v: Any, path: str, *, allow_none: bool = False) -> float:
        if v is None and allow_none:
            return math.nan
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SpecError(f"{path}: expected a number, got {v!r}")
        f = float(v)
        if math.isnan(f):
            raise SpecError(f"{path}: NaN is not allowed")
        return f

    def field(self, name: Any, path: str) -> _FieldRef:
        if not isinstance(name, str) or "." not in name:
            raise SpecError(
                f"{path}: field {name!r} must be written SOURCE.NAME with SOURCE one of "
                f"{sorted(self.layouts)} (x = state x_t, u = control u_t, next = target)"
            )
        src, fname = name.split(".", 1)
        if src not in self.layouts:
            raise SpecError(f"{path}: unknown field source {src!r} in {name!r}; use one of {sorted(self.layouts)}")
        lay = self.layouts[src]
        if fname not in lay.names:
            raise SpecError(f"{path}: unknown field {name!r}; {SOURCES[src]} fields are {list(lay.names)}")
        return _FieldRef(src, lay.index(fname))

    def region(self, r: Any, path: str) -> Region | None:
        if r is None:
            return None
        if not isinstance(r, Mapping) or len(r) != 1:
            raise SpecError(
                f"{path}: a region is null or a mapping with exactly one of "
                "box, norm, not, all_of, any_of"
            )
        (kind, body), = r.items()
        p = f"{path}.{kind}"
        if kind == "box":
            if not isinstance(body, Mapping) or not body:
                raise SpecError(f"{p}: expected a non-empty mapping FIELD: [lo, hi]")
            bounds = []
            for fname, lohi in body.items():
                ref = self.field(fname, f"{p}.{fname}")
                if not isinstance(lohi, (list, tuple)) or len(lohi) != 2:
                    raise SpecError(f"{p}.{fname}: expected [lo, hi] (null for an open end), got {lohi!r}")
                lo = self.number(lohi[0], f"{p}.{fname}[0]", allow_none=True)
                hi = self.number(lohi[1], f"{p}.{fname}[1]", allow_none=True)
                lo = -math.inf if math.isnan(lo) else lo
                hi = math.inf if math.isnan(hi) else hi
                if lo > hi:
                    raise SpecError(f"{p}.{fname}: empty interval [{lo}, {hi}]")
                bounds.append((ref, lo, hi))
            return _Box(bounds)
        if kind == "norm":
            self.check_keys(body, p, {"fields", "ord", "min", "max"})
            fields = body.get("fields")
            if not isinstance(fields, list) or not fields:
                raise SpecError(f"{p}.fields: expected a non-empty list of fields")
            refs = [self.field(f, f"{p}.fields[{i}]") for i, f in enumerate(fields)]
            ord_raw = body.get("ord", 2)
            ords = {1: 1.0, 2: 2.0, "inf": math.inf, math.inf: math.inf}
            if ord_raw not in ords:
                raise SpecError(f"{p}.ord: expected 1, 2 or inf, got {ord_raw!r}")
            if "min" not in body and "max" not in body:
                raise SpecError(f"{p}: give min and/or max")
            lo = self.number(body.get("min", 0.0), f"{p}.min")
            hi = self.number(body.get("max", math.inf), f"{p}.max") if "max" in body else math.inf
            if lo > hi:
                raise SpecError(f"{p}: min {lo} > max {hi}")
            return _Norm(refs, ords[ord_raw], lo, hi)
        if kind == "not":
            inner = self.region(body, p)
            if inner is None:
                raise SpecError(f"{p}: 'not' needs a region (the complement of everything is empty)")
            return _Not(inner)
        if kind in ("all_of", "any_of"):
            if not isinstance(body, list) or not body:
                raise SpecError(f"{p}: expected a non-empty list of regions")
            parts: list[Region] = []
            for i, b in enumerate(body):
                sub = self.region(b, f"{p}[{i}]")
                parts.append(_Everything() if sub is None else sub)
            return _AllOf(parts) if kind == "all_of" else _AnyOf(parts)
        raise SpecError(f"{path}: unknown region kind {kind!r}; use box, norm, not, all_of or any_of")

    def term(self, t: Any, path: str, *, is_constraint: bool) -> Term:
        allowed = {"loss", "fields", "region", "mean", "huber_delta"}
        if is_constraint:
            allowed |= {"name", "eps"}
        self.check_keys(t, path, allowed)
        loss = t.get("loss", "l2")
        if loss not in LOSS_TYPES:
            raise SpecError(f"{path}.loss: unknown loss {loss!r}; use one of {list(LOSS_TYPES)}")
        target = self.layouts["next"]
        fnames = t.get("fields") or list(target.names)
        if not isinstance(fnames, list):
            raise SpecError(f"{path}.fields: expected a list of target field names")
        idx = []
        for i, f in enumerate(fnames):
            name = f[5:] if isinstance(f, str) and f.startswith("next.") else f
            if name not in target.names:
                raise SpecError(
                    f"{path}.fields[{i}]: unknown target field {f!r}; target fields are {list(target.names)}"
                )
            idx.append(target.index(name))
        mean = t.get("mean", "conditional" if is_constraint else "unconditional")
        if mean not in MEAN_TYPES:
            raise SpecError(f"{path}.mean: expected one of {list(MEAN_TYPES)}, got {mean!r}")
        delta = self.number(t.get("huber_delta", 1.0), f"{path}.huber_delta")
        if delta <= 0:
            raise SpecError(f"{path}.huber_delta: must be > 0, got {delta}")
        region = self.region(t.get("region"), f"{path}.region")
        if not is_constraint:
            return Term("objective", loss, tuple(idx), region, mean, 0.0, delta)
        name = t.get("name", path.replace("[", "_").rstrip("]"))
        if not isinstance(name, str) or not name.replace("_", "").isalnum():
            raise SpecError(f"{path}.name: use letters, digits and underscores, got {name!r}")
        if "eps" not in t:
            raise SpecError(f"{path}.eps: missing (the constraint bound, > 0)")
        eps = self.number(t["eps"], f"{path}.eps")
        if not eps > 0 or math.isinf(eps):
            raise SpecError(f"{path}.eps: must be a finite number > 0, got {eps}")
        return Term(name, loss, tuple(idx), region, mean, eps, delta)
