"""test_docs_names - every module, path and ``python -m``/``python -c`` line the documents name
exists under the layered layout (issue 14).

Read: README.md, busconfig/README.md and docs/*.md. Checked: each ``python -m MODULE`` names a
module that can be found and starts (``--help``, from the checkout's root); each
``python -c "..."`` compiles and its ``import``/``from ... import`` lines resolve (the module is
found, the imported names are its attributes); each path in backticks under the repository's top
folders exists; each dotted ``chcos.``/``drivers.``/``tools.`` name in backticks is a module or an
attribute of one. The commands themselves are run elsewhere (the tutorial's by
test_integrator_tutorial, ``chcos run`` by test_packaging).
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", ROOT / "busconfig" / "README.md", *sorted((ROOT / "docs").glob("*.md")),
        *sorted((ROOT / "docs").glob("*/*.md"))]
TOPS = ("chcos", "drivers", "busconfig", "vcan_tests", "tools", "docs", ".ci")

PY_M = re.compile(r"python3?\s+-m\s+([A-Za-z_][\w.]*)")
PY_C = re.compile(r"""python3?\s+-c\s+(?:"((?:[^"\\]|\\.)*)"|'([^']*)')""")
TICKED = re.compile(r"`([^`\s]+)`")
#: entry-point groups: dotted like a module, but names in pyproject.toml, not modules.
GROUPS = {"chcos.drivers"}
PLACEHOLDER = re.compile(r"(^|[/.])[A-Z]{2,}($|[/.])")   # chcos/NAME, tools.NAME


def rel(doc: Path) -> str:
    return doc.relative_to(ROOT).as_posix()


def resolve(dotted: str) -> bool:
    """True when ``dotted`` is a module, or an attribute (chain) of the longest module prefix."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)   # a module that warns on import
        return _resolve(dotted)


def _resolve(dotted: str) -> bool:
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        name = ".".join(parts[:cut])
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            continue
        if cut == len(parts):
            return True
        obj: object = importlib.import_module(name)
        for attr in parts[cut:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_python_m_modules_exist() -> None:
    bad = [f"{rel(d)}: python -m {m}" for d in DOCS for m in PY_M.findall(d.read_text())
           if not PLACEHOLDER.search(m) and importlib.util.find_spec(m.rstrip(".")) is None]
    assert not bad, "\n".join(bad)


@pytest.mark.slow
def test_python_m_modules_run() -> None:
    """Each documented ``python -m`` module starts from the checkout's root (``--help``)."""
    names = sorted({m.rstrip(".") for d in DOCS for m in PY_M.findall(d.read_text())
                    if not PLACEHOLDER.search(m)})
    assert names
    procs = {m: subprocess.Popen([sys.executable, "-m", m, "--help"], cwd=ROOT, text=True,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE) for m in names}
    bad = []
    for m, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        if proc.returncode != 0 or not out:
            bad.append(f"python -m {m} --help exited {proc.returncode}: {err[-500:]}")
    assert not bad, "\n".join(bad)


def test_python_c_lines_compile_and_their_imports_resolve() -> None:
    bad = []
    seen = 0
    for doc in DOCS:
        for dq, sq in PY_C.findall(doc.read_text()):
            code = (dq.replace('\\"', '"') if dq else sq)
            seen += 1
            try:
                tree = ast.parse(code)
            except SyntaxError as e:
                bad.append(f"{rel(doc)}: python -c {code[:60]!r}: {e}")
                continue
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    bad += [f"{rel(doc)}: import {a.name}" for a in node.names
                            if not resolve(a.name)]
                elif isinstance(node, ast.ImportFrom) and node.module:
                    bad += [f"{rel(doc)}: from {node.module} import {a.name}" for a in node.names
                            if not resolve(f"{node.module}.{a.name}")]
    assert seen, "no python -c line found: the pattern is broken"
    assert not bad, "\n".join(bad)


def test_paths_and_module_names_in_backticks_exist() -> None:
    bad = []
    for doc in DOCS:
        for token in TICKED.findall(doc.read_text()):
            token = token.rstrip(".,;:)")
            if PLACEHOLDER.search(token) or token in GROUPS:
                continue
            head = token.split("/")[0]
            if "/" in token and head in TOPS and not any(c in token for c in "*{<$"):
                if not (ROOT / token.split("::")[0].split(":")[0]).exists():
                    bad.append(f"{rel(doc)}: path {token}")
            elif re.fullmatch(r"(chcos|drivers|tools)(\.[A-Za-z_]\w*)+(\(\))?", token):
                name = token.removesuffix("()")
                if not resolve(name):
                    bad.append(f"{rel(doc)}: name {name}")
    assert not bad, "\n".join(bad)


def test_the_groups_are_entry_point_groups() -> None:
    text = (ROOT / "pyproject.toml").read_text()
    assert all(f'[project.entry-points."{g}"]' in text for g in GROUPS)


@pytest.mark.parametrize("name, expected", [
    ("chcos.user.context.TaskContext", True), ("chcos.resources.path", True),
    ("chcos.usrmgr.TaskContext", False), ("chcos.sysmgr", False), ("chcos.kernel.nothing", False)])
def test_resolve(name: str, expected: bool) -> None:
    assert resolve(name) is expected
