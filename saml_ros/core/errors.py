"""The base of saml_ros's own errors: :class:`SamlError`.

Every error saml_ros raises on purpose (a bad spec, system file, checkpoint, bag, parameter, device, command ...)
derives from :class:`SamlError`, so a node or a command line catches the whole family in one place and reports it
(``except SamlError``), while a bug (``TypeError``, ``KeyError`` ...) still ends in a traceback. Each error keeps the
built-in base its callers caught before (``ValueError`` for bad input, ``RuntimeError`` for a state that cannot go
on), so ``except ValueError`` still catches, e.g., a :class:`~saml_ros.core.spec.SpecError`.

The errors live beside the code that raises them (``SpecError`` in :mod:`saml_ros.core.spec`, ``CheckpointError`` in
:mod:`saml_ros.core.model.checkpoint`, ...); :func:`saml_errors` lists them (documentation, tests).
"""

from __future__ import annotations


class SamlError(Exception):
    """An error saml_ros raises on purpose; its message says what was wrong and, where it can, how to fix it."""


def saml_errors() -> list[type[SamlError]]:
    """Every subclass of :class:`SamlError` defined by the modules imported so far, sorted by qualified name."""
    out: list[type[SamlError]] = []
    todo = list(SamlError.__subclasses__())
    while todo:
        cls = todo.pop()
        if cls not in out:
            out.append(cls)
            todo += cls.__subclasses__()
    return sorted(out, key=lambda c: f"{c.__module__}.{c.__qualname__}")
