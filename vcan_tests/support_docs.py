"""Support for the tests that run a document's commands verbatim (the tutorials): the commands of
its fenced blocks, in order (:func:`tools.doccmds.doc_commands`, shared with the benchmarks)."""

from __future__ import annotations

from tools.doccmds import doc_commands

__all__ = ["doc_commands"]
