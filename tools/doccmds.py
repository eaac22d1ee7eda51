"""doccmds - the shell commands of a Markdown document's fenced blocks, in order (for the tests
that run a tutorial verbatim and for the benchmarks that build a tutorial's cell)."""

from __future__ import annotations

import re
from pathlib import Path


def doc_commands(path: Path, kind: str = "sh") -> list[str]:
    """Every command of the ``kind`` blocks of the Markdown file at ``path``, in order: for
    ``sh`` one per non-blank line, a here-document (``<<'EOF'`` to its end marker) as one
    command; for any other kind each block whole."""
    blocks = re.findall(rf"^```{kind}\n(.*?)^```", path.read_text(encoding="utf-8"),
                        flags=re.S | re.M)
    if kind != "sh":
        return blocks
    out: list[str] = []
    for block in blocks:
        lines = iter(block.splitlines())
        for line in lines:
            if not line.strip():
                continue
            m = re.search(r"<<'(\w+)'", line)
            if m:
                body = [line]
                for more in lines:
                    body.append(more)
                    if more == m.group(1):
                        break
                out.append("\n".join(body))
            else:
                out.append(line)
    return out
