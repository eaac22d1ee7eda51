"""loader - find a task's code from an install reference (the thesis' load of an object file).

References: ``pkg.module:function``; ``pkg.module`` (its ``main`` function); a bare name such as
``A1``, looked up as ``A1.py`` in the task path directories (the thesis' object file ``A1``);
or a file path ``dir/A1.py[:function]``. The function must be an ``async def`` taking
``(ctx, command)``.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import sys
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

from chcos.errors import InstallError
from chcos.tables.tasks import TaskFunc

_DEFAULT_FUNCS = ("main", "task")


def _from_module(mod: ModuleType, func: str | None, ref: str) -> TaskFunc:
    names = (func,) if func else (*_DEFAULT_FUNCS, mod.__name__.rsplit(".", 1)[-1])
    for n in names:
        if n is None:
            continue
        obj = getattr(mod, n, None)
        if obj is not None:
            if not inspect.iscoroutinefunction(obj):
                raise InstallError(f"task code {ref}: {n} is not an async def function")
            return obj  # type: ignore[no-any-return]
    want = func or " or ".join(_DEFAULT_FUNCS)
    raise InstallError(f"task code {ref}: module {mod.__name__} has no function {want}")


def _load_file(path: Path, ref: str) -> ModuleType:
    digest = hashlib.sha1(str(path.resolve()).encode()).hexdigest()[:10]
    name = f"chcos_task_{path.stem}_{digest}"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise InstallError(f"task code {ref}: cannot load {path}")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    try:
        spec.loader.exec_module(mod)
    except Exception as exc:
        del sys.modules[name]
        raise InstallError(f"task code {ref}: {path} failed to load: "
                           f"{type(exc).__name__}: {exc}") from exc
    return mod


def resolve(ref: str, task_path: Sequence[str | Path] = ()) -> TaskFunc:
    """The task function ``ref`` names. Raises InstallError saying what was looked for where."""
    target, _, func = ref.partition(":")
    func_name = func or None
    if target.endswith(".py") or "/" in target:
        path = Path(target)
        if not path.is_absolute():
            for d in task_path:
                if (Path(d) / path).is_file():
                    path = Path(d) / path
                    break
        if not path.is_file():
            raise InstallError(f"task code {ref}: no file {target}")
        return _from_module(_load_file(path, ref), func_name, ref)
    if "." not in target:
        for d in task_path:
            candidate = Path(d) / f"{target}.py"
            if candidate.is_file():
                return _from_module(_load_file(candidate, ref), func_name, ref)
    try:
        mod = importlib.import_module(target)
    except ImportError as exc:
        where = ", ".join(str(d) for d in task_path) or "no task path"
        raise InstallError(f"task code {ref}: no module {target} (looked in {where} and on "
                           f"the Python path: {exc})") from exc
    return _from_module(mod, func_name, ref)
