"""One error base (issue 31 item 3): every exception class saml_ros defines derives from :class:`SamlError` and keeps
the built-in base its callers catch (``ValueError`` for bad input), so ``except SamlError`` in a node reports the
whole family and ``except ValueError`` still catches what it caught."""

from __future__ import annotations

import ast
import importlib

import pytest
from helpers import REPO

from saml_ros.core.errors import SamlError, saml_errors

BUILTIN_BASES = {"Exception", "ValueError", "RuntimeError", "OSError", "TypeError", "KeyError", "LookupError"}
#: exception classes that are not errors: a command line's private early exit
NOT_ERRORS = {"saml_ros.offline.cli._Refused", "saml_ros.core.errors.SamlError"}


def _exception_classes() -> dict[str, list[str]]:
    """``module.Class -> [base names]`` for every class of the packages whose bases name a built-in exception or
    ``SamlError`` (read from the source, so a new module's error is seen without importing it)."""
    out = {}
    for pkg in ("saml_ros", "msg_schemas", "sim_nodes"):
        for path in sorted((REPO / pkg).rglob("*.py")):
            mod = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ClassDef):
                    bases = [ast.unparse(b).rsplit(".", 1)[-1] for b in node.bases]
                    if set(bases) & (BUILTIN_BASES | {"SamlError"}):
                        out[f"{mod}.{node.name}"] = bases
    return out


def test_every_error_class_derives_from_saml_error() -> None:
    classes = _exception_classes()
    assert len(classes) >= 15, classes  # the checker sees the package's errors
    missing = sorted(name for name, bases in classes.items()
                     if name not in NOT_ERRORS and not {"SamlError"} & set(bases)
                     and not any(_is_saml(name.rsplit(".", 1)[0], b) for b in bases))
    assert not missing, f"errors not derived from SamlError: {missing}"


def _is_saml(module: str, base: str) -> bool:
    """A base class named ``base`` that is itself one of saml_ros's errors (``IncompatibleCheckpoint(CheckpointError)``)."""
    if base in BUILTIN_BASES:
        return False
    cls = getattr(importlib.import_module(module), base, None)
    return isinstance(cls, type) and issubclass(cls, SamlError)


@pytest.mark.parametrize(("path", "builtin"), [
    ("saml_ros.core.spec.SpecError", ValueError),
    ("saml_ros.systems.system_file.SystemFileError", ValueError),
    ("saml_ros.core.params.ParamErrors", ValueError),
    ("saml_ros.core.runtime.device.DeviceError", ValueError),
    ("saml_ros.core.worlds.sim_core.CommandRejected", ValueError),
    ("saml_ros.core.model.io.UnhealthyModel", ValueError),
    ("saml_ros.core.model.io.IncompatibleCheckpoint", Exception),
    ("saml_ros.core.online.resume.ResumeError", RuntimeError),
    ("msg_schemas.base.SchemaError", ValueError),
    ("saml_ros.bags.io.BagError", ValueError),
    ("saml_ros.core.online.config.TrainingStartError", ValueError),
    ("saml_ros.core.online.process.StartCancelled", Exception),
])
def test_errors_keep_the_base_their_callers_catch(path: str, builtin: type[Exception]) -> None:
    module, name = path.rsplit(".", 1)
    cls = getattr(importlib.import_module(module), name)
    assert issubclass(cls, SamlError) and issubclass(cls, builtin)
    assert cls in saml_errors()
