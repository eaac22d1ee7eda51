"""support_env - what a test says of its environment: ``require`` (skip locally, fail under
CI=true), ``opt_in`` (the only skips allowed under CI) and ``under_ci``. Below every other helper
(conftest, uml, support_weldcell import it; it imports none of them), so the helpers need no
circle to share it; conftest re-exports the names for the tests that import them from there."""

from __future__ import annotations

import os

import pytest

__all__ = ["OPT_IN", "opt_in", "require", "under_ci"]

OPT_IN = "opt-in: "
"""Prefix of the reason of every allowed skip (see :func:`opt_in`)."""


def under_ci() -> bool:
    """True under CI (the CI variable set to true/1/yes), where nothing may skip for a missing
    tool."""
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def require(ok: object, what: str) -> None:
    """Declare an environment requirement of the running test: when ``ok`` is false, the test
    is skipped with ``missing: what`` locally and fails with that message under CI (see
    :func:`under_ci`). ``what`` names the missing thing and how to get it, e.g.
    ``"/usr/bin/chromium (apt-get install chromium)"``."""
    if ok:
        return
    if under_ci():
        pytest.fail(f"missing under CI=true: {what}", pytrace=False)
    pytest.skip(f"missing: {what}")


def opt_in(variable: str, what: str) -> None:
    """Skip the running test unless the environment variable ``variable`` is 1: the only kind of
    skip allowed under CI. ``what`` says what the run costs (it lands in the skip reason)."""
    if os.environ.get(variable) != "1":
        pytest.skip(f"{OPT_IN}{what}; set {variable}=1 to run it")
