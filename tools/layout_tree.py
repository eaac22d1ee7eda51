"""layout_tree - the folders of chcos/ and drivers/ with their module and line counts, at a git
revision or in the working tree, as Markdown (the before/after tree of issue 14's note).

Usage: ``python -m tools.layout_tree [--rev REV]... [--over N]``: one section per revision (the
working tree when no ``--rev`` is given, or with ``--rev WORKTREE``). For each folder: the number
of Python modules directly in it, their lines, and the lines of everything below it; then the
modules over N lines (default 400). Run from the checkout; needs git for ``--rev``.
Raises SystemExit naming the revision when git cannot read it.
"""

from __future__ import annotations

import argparse
import subprocess
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TOPS = ("chcos", "drivers")
WORKTREE = "WORKTREE"


def modules(rev: str) -> dict[str, int]:
    """Every ``*.py`` under chcos/ and drivers/ at ``rev`` (or the working tree): path -> lines."""
    if rev == WORKTREE:
        return {p.relative_to(ROOT).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
                for top in TOPS for p in sorted((ROOT / top).rglob("*.py"))
                if "__pycache__" not in p.parts}
    listed = subprocess.run(["git", "ls-tree", "-r", "--name-only", rev, "--", *TOPS], cwd=ROOT,
                            capture_output=True, text=True, check=False)
    if listed.returncode:
        raise SystemExit(f"layout_tree: git cannot list revision {rev!r}: {listed.stderr.strip()}")
    out = {}
    for path in listed.stdout.split():
        if path.endswith(".py"):
            text = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, capture_output=True,
                                  text=True, check=True).stdout
            out[path] = len(text.splitlines())
    return out


def render(rev: str, over: int) -> str:
    """The Markdown section of one revision."""
    mods = modules(rev)
    own: dict[str, list[int]] = defaultdict(list)
    below: dict[str, int] = defaultdict(int)
    for path, lines in mods.items():
        folder = path.rpartition("/")[0]
        own[folder].append(lines)
        parts = folder.split("/")
        for i in range(1, len(parts) + 1):
            below["/".join(parts[:i])] += lines
    title = "working tree" if rev == WORKTREE else f"`{rev}`"
    rows = [f"### {title}: {len(mods)} modules, {sum(mods.values()):,} lines", "",
            "```", f"{'folder':<34}{'modules':>8}{'lines':>8}{'with subfolders':>17}"]
    for folder in sorted(below):
        depth = folder.count("/")
        name = "  " * depth + folder.rpartition("/")[2] + "/"
        rows.append(f"{name:<34}{len(own[folder]):>8}{sum(own[folder]):>8,}"
                    f"{below[folder]:>17,}")
    rows += ["```", ""]
    big = sorted(((n, p) for p, n in mods.items() if n > over), reverse=True)
    rows.append(f"Modules over {over} lines: " + (", ".join(f"`{p}` ({n})" for n, p in big)
                                                 if big else "none") + ".")
    return "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> None:
    """Print one section per ``--rev``."""
    ap = argparse.ArgumentParser(prog="python -m tools.layout_tree", description=__doc__)
    ap.add_argument("--rev", action="append", default=None,
                    help=f"a git revision, or {WORKTREE} (default: the working tree)")
    ap.add_argument("--over", type=int, default=400, help="list modules over this many lines")
    args = ap.parse_args(argv)
    print("\n".join(render(rev, args.over) for rev in (args.rev or [WORKTREE])))


if __name__ == "__main__":
    main()
