"""The suite's own rules (vcan_tests/conftest.py): a missing environment piece skips locally and
fails under CI=true naming it; any other skip fails under CI too; opt-in runs skip everywhere."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from vcan_tests.uml import REPO_ROOT

PROBE = '''
import pytest

from vcan_tests.conftest import opt_in, require


def test_needs_a_tool() -> None:
    require(False, "the frobnicator on PATH (apt-get install frob)")


def test_skips_by_hand() -> None:
    pytest.skip("no frob here")


@pytest.mark.skipif(True, reason="frob absent")
def test_skipif_marker() -> None:
    pass


def test_long_run() -> None:
    opt_in("CHCOS_TEST_NEVER_SET", "a run of a week")


def test_ordinary() -> None:
    require(True, "nothing")
'''


def _run(tmp_path: Path, ci: str | None) -> dict[str, tuple[str, str]]:
    """Run PROBE under the suite's conftest; outcome and message per test name."""
    (tmp_path / "test_probe.py").write_text(PROBE)
    junit = tmp_path / "out.xml"
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "CHCOS_TEST_NEVER_SET")}
    env["PYTHONPATH"] = str(REPO_ROOT)
    if ci is not None:
        env["CI"] = ci
    subprocess.run([sys.executable, "-m", "pytest", "-p", "vcan_tests.conftest", "-p",
                    "no:cacheprovider", "--rootdir", str(tmp_path), f"--junitxml={junit}",
                    "test_probe.py"], cwd=tmp_path, env=env, capture_output=True, text=True,
                   timeout=120, check=False)
    result = {}
    for case in ET.parse(junit).iter("testcase"):
        kinds = [c for c in case if c.tag in ("failure", "error", "skipped")]
        result[str(case.get("name"))] = ((kinds[0].tag, kinds[0].get("message", "")) if kinds
                                         else ("passed", ""))
    return result


def test_without_ci_environment_gaps_skip_with_their_reason(tmp_path: Path) -> None:
    got = _run(tmp_path, None)
    assert got["test_needs_a_tool"] == (
        "skipped", "missing: the frobnicator on PATH (apt-get install frob)")
    assert got["test_skips_by_hand"] == ("skipped", "no frob here")
    assert got["test_skipif_marker"] == ("skipped", "frob absent")
    assert got["test_long_run"][0] == "skipped"
    assert "set CHCOS_TEST_NEVER_SET=1" in got["test_long_run"][1]
    assert got["test_ordinary"] == ("passed", "")


def test_under_ci_only_opt_in_runs_skip(tmp_path: Path) -> None:
    got = _run(tmp_path, "true")
    kind, message = got["test_needs_a_tool"]
    assert kind == "failure"
    assert "missing under CI=true: the frobnicator on PATH (apt-get install frob)" in message
    for name, reason in (("test_skips_by_hand", "no frob here"),
                         ("test_skipif_marker", "frob absent")):
        kind, message = got[name]
        assert kind in ("failure", "error"), got  # skipif acts in setup: an error
        assert "skipped under CI=true" in message and reason in message, message
    assert got["test_long_run"][0] == "skipped"
    assert got["test_ordinary"] == ("passed", "")
