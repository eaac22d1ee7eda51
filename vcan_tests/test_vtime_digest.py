"""A virtual-time run gives the same answer on every machine (issue 47): the welding job's run
digest (weld length and band, every device's readings and commands, every task's executions, the
event log with its virtual times, the shutdown's safe values: chcos.apps.weld.rundigest) is the
same on a quiet machine, with every core loaded by busy processes, and with PYTHONHASHSEED
varied, each run in a fresh interpreter (python -m tools.run_digest).

The protocol-free binding holds now. The simulated buses do not yet: their drivers and peers
still hand frames between threads whose timing decides the order of interrupts within an instant
(the list is in the report on issue 47); that case is an expected failure until the bus
branches of issue 47 are merged, and must then pass (strict).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from chcos.system.digest import differences
from vcan_tests.support_vtime import busy_cores, digest_in_subprocess

#: virtual seconds of each run: the direct job's inspection and the first quarter of its weld
#: (the loaded run costs every core for as long as it runs), and a stretch of the buses job long
#: enough for its threads to part the runs
SECONDS = {"direct": 45.0, "buses": 15.0}


def _three_runs(binding: str, where: Path) -> list[tuple[str, str, dict[str, object]]]:
    """(what, digest, document) of a quiet run, a run with every core busy and one more quiet
    run with another hash seed."""
    out = []
    digest, doc = digest_in_subprocess(binding, SECONDS[binding], 0, where / "quiet.json")
    out.append(("quiet, PYTHONHASHSEED=0", digest, doc))
    with busy_cores():
        digest, doc = digest_in_subprocess(binding, SECONDS[binding], 1, where / "loaded.json")
    out.append(("every core busy, PYTHONHASHSEED=1", digest, doc))
    digest, doc = digest_in_subprocess(binding, SECONDS[binding], 4242, where / "seed.json")
    out.append(("quiet, PYTHONHASHSEED=4242", digest, doc))
    return out


def _assert_same(runs: list[tuple[str, str, dict[str, object]]]) -> None:
    what0, digest0, doc0 = runs[0]
    for what, digest, doc in runs[1:]:
        assert digest == digest0, (f"{what} parts from {what0}:\n  "
                                   + "\n  ".join(differences(doc0, doc)))


@pytest.mark.slow
def test_the_direct_binding_gives_one_digest_quiet_loaded_and_hash_seeded(
        tmp_path: Path) -> None:
    runs = _three_runs("direct", tmp_path)
    _assert_same(runs)
    weld = runs[0][2]["weld"]
    assert isinstance(weld, dict)
    # worth comparing: the gap was inspected and the weld is under way, in band
    assert weld["welded_mm"] > 50.0 and weld["in_band_mm"] >= 0.95 * weld["welded_mm"], weld


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 47: the simulated buses' drivers and peers still "
                   "hand frames between threads (interrupt order within an instant depends on "
                   "their timing); passes once the bus branches of issue 47 are merged")
def test_the_simulated_buses_give_one_digest_quiet_loaded_and_hash_seeded(
        tmp_path: Path) -> None:
    runs = _three_runs("buses", tmp_path)
    system = runs[0][2]["system"]
    assert isinstance(system, dict)
    assert sum(d["readings"] for d in system["devices"].values()) > 10_000
    _assert_same(runs)
