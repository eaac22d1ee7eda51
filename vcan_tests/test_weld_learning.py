"""The tip-stuck learned recognizer: over 5 repeated runs of a scenario that sticks the tip, the
cell reacts earlier once it has learned the precursor (the arc voltage sinking as the wire stubs
into the pool) than the hard-coded recognizer (the short circuit of a frozen tip); the learned
data persists between runs beside the map and can be reset."""

from __future__ import annotations

import io
import json
from pathlib import Path

from chcos.apps.weld.learning import forget, learning_curve, one_run
from chcos.user.knowledge import LearnedPattern, Store


def test_learned_recognizer_reacts_earlier_on_repeated_runs(tmp_path: Path) -> None:
    out = io.StringIO()
    rows = learning_curve(3, workdir=tmp_path, out=out)
    print(out.getvalue())
    first, later = rows[0], rows[1:]
    # run 1: nothing learned yet; the hard-coded recognizer reacts once the tip has frozen
    assert first["reaction"] == "hard-coded" and first["froze"], first
    assert first["after_s"] is not None and first["after_s"] >= 2.0  # the precursor lasts 2 s
    # runs 2 and 3: the learned recognizer reacts before the freeze, and the tip never freezes
    for row in later:
        assert row["reaction"] == "learned" and not row["froze"], rows
        assert row["after_s"] is not None and row["after_s"] < 1.0 < first["after_s"], rows
    assert all(r["outcome"] == "welded" and r["false_alarms"] == 0 for r in rows), rows
    assert all(r["welded_mm"] >= 0.99 * r["seam_mm"] for r in rows), rows
    table = out.getvalue().splitlines()
    assert len([ln for ln in table if "50.00 s" in ln]) == 3
    # persisted beside the map between runs, and resettable
    learned = tmp_path / "learned" / "C1-tip.json"
    doc = json.loads(learned.read_text())
    assert doc["features"] == ["volts"] and len(doc["examples"]) >= 1
    assert all(e["volts"] < -1.0 for e in doc["examples"])  # the voltage sank before the freeze
    forget(tmp_path)
    assert not learned.exists()
    assert not LearnedPattern(["volts"], Store.beside(tmp_path, "C1-tip")).examples


def test_a_freeze_without_a_precursor_teaches_nothing_and_a_fault_free_run_raises_no_alarm(
        tmp_path: Path) -> None:
    """A tip that freezes with no precursor (nothing in the arc voltage before it differs from
    normal welding) leaves C1 nothing to learn: no learned data is written, and the next,
    fault-free run in the same directory has no learned reaction (no false "sticking")."""
    first = one_run(tmp_path, "tip-stuck@t=50s")
    assert first["reaction"] == "hard-coded" and first["outcome"] == "welded", first
    assert not (tmp_path / "learned" / "C1-tip.json").exists()
    second = one_run(tmp_path, "")
    assert second["reaction"] == "none" and second["false_alarms"] == 0, second
    assert second["outcome"] == "welded", second


def test_precursor_parameter_parses_round_trips_and_is_checked() -> None:
    import pytest

    from chcos.apps.weld import parse_scenario
    from chcos.apps.weld.model import WeldCell
    from chcos.errors import ConfigError

    (fault,) = parse_scenario("tip-stuck(precursor=1500ms)@t=50s").faults
    assert fault.precursor == 1.5
    assert fault.describe() == "tip-stuck(precursor=1.5s)@t=50.0s"
    with pytest.raises(ConfigError, match="precursor"):
        parse_scenario("gas-empty(precursor=1s)")
    with pytest.raises(ConfigError):
        parse_scenario("tip-stuck(precursor=-1s)")
    # without the arc nothing stubs: the precursor ends at once
    cell = WeldCell()
    cell.inject(fault.__class__("tip-stuck", precursor=1.0))
    cell.step(0.01)
    assert cell.stubbing is None and not cell.tip_stuck
