"""Run independent units (sweep points, seeds, trials, datasets) in this process or on Ray, with the same results.

``ray`` names the backend: ``None`` / ``"none"`` runs the units here one after the other (the default, no Ray
needed); ``"local"`` starts a private Ray instance on this machine for the run (``num_cpus`` CPUs, default all)
and stops it afterwards; ``"auto"`` joins the running cluster (``ray start --head`` first) and any other value
is a cluster address (``ray://host:10001``, ``host:6379``). A unit is ``fn(item)`` with ``fn`` a module-level
function; each unit runs with one torch intra-op thread everywhere, and its randomness comes only from its item
(seeds), so a unit gives the same numbers in-process and on any Ray worker. Results come back in item order.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

from saml_ros.core.errors import SamlError

T = TypeVar("T")
R = TypeVar("R")

#: what ``--ray`` accepts besides a cluster address
RAY_MODES = ("none", "local", "auto")
#: object store of a ``local`` instance (bytes): the units exchange small arrays only
LOCAL_OBJECT_STORE = 200 * 1024 * 1024


class RayUnavailable(SamlError, RuntimeError):
    """``--ray`` was asked for but the ``ray`` package is not installed, or the cluster cannot be reached."""


def run_unit(fn: Callable[[T], R], item: T) -> R:
    """``fn(item)`` with one torch intra-op thread (how every unit runs, in-process or on a Ray worker)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return fn(item)
    finally:
        torch.set_num_threads(threads)


def check_ray(ray: str | None) -> str | None:
    """The normalized backend (``None`` for in-process); :class:`RayUnavailable` when Ray is needed but missing."""
    if ray is None or ray == "none":
        return None
    try:
        import ray as _ray  # noqa: F401
    except ImportError:
        raise RayUnavailable(f"--ray {ray}: the ray package is not installed (pip install ray)") from None
    return ray


def _package_paths() -> list[str]:
    """Source roots of saml_ros and msg_schemas (what Ray workers need on their path)."""
    import msg_schemas
    import saml_ros

    return sorted({str(Path(m.__file__).resolve().parents[1]) for m in (saml_ros, msg_schemas)})  # type: ignore[arg-type]


@contextlib.contextmanager
def ray_session(ray: str | None, num_cpus: int | None = None) -> Iterator[None]:
    """Keep one Ray connection (``local``: a private instance) open for every :func:`map_units` call inside the
    block; a no-op for in-process runs or when Ray is already initialized (then whoever started it stops it)."""
    backend = check_ray(ray)
    if backend is None:
        yield
        return
    import ray as ray_mod

    if ray_mod.is_initialized():
        yield
        return
    paths = _package_paths()
    env = {"PYTHONPATH": os.pathsep.join([*paths, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    try:
        if backend == "local":
            ray_mod.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                         object_store_memory=LOCAL_OBJECT_STORE, runtime_env={"env_vars": env})
        else:
            import msg_schemas
            import saml_ros

            ray_mod.init(address=backend, log_to_driver=False, runtime_env={"py_modules": [saml_ros, msg_schemas]})
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise RayUnavailable(f"--ray {backend}: cannot start or reach Ray: {exc}") from None
    try:
        yield
    finally:
        ray_mod.shutdown()


def map_units(fn: Callable[[T], R], items: Iterable[T], ray: str | None = None, num_cpus: int | None = None,
              on_result: Callable[[int, R], None] | None = None) -> list[R]:
    """``[fn(item) for item in items]`` on the backend ``ray`` (module docstring); ``on_result(index, result)``
    is called as each unit finishes (for progress)."""
    todo: Sequence[T] = list(items)
    if check_ray(ray) is None:
        out = []
        for i, item in enumerate(todo):
            out.append(run_unit(fn, item))
            if on_result is not None:
                on_result(i, out[-1])
        return out
    import ray as ray_mod

    with ray_session(ray, num_cpus):
        remote: Any = ray_mod.remote(num_cpus=1)(run_unit)
        refs = [remote.remote(fn, item) for item in todo]
        index = {ref: i for i, ref in enumerate(refs)}
        results: list[Any] = [None] * len(refs)
        pending = list(refs)
        while pending:
            done, pending = ray_mod.wait(pending, num_returns=1)
            for ref in done:
                i = index[ref]
                results[i] = ray_mod.get(ref)
                if on_result is not None:
                    on_result(i, results[i])
        return results
