"""The trace format and its diff (issue 52): records written and read back exactly (floats to the
bit, NaN, strings with spaces and quotes, lists), gzip with the same bytes every time, a bad line
named by file and line; the diff's signal and sequence rules with tolerances; MCAP read back by
the mcap library's own reader; the subject of a system event."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from chcos.cli.diff import main as diff_main
from chcos.hil.diff import compare, parse_tolerances
from chcos.hil.observe import Kind, Record, event_subject
from chcos.hil.trace import (
    Trace,
    TraceError,
    TraceRecorder,
    entry_of,
    format_entry,
    parse_text,
    read_trace,
    write_mcap,
)


def _trace(*records: Record, **header: str) -> Trace:
    rec = TraceRecorder(**header)
    for r in records:
        rec.record(r)
    return rec.trace


RECORDS = (
    Record(0.1, Kind.VALUE, "level", 0.1 + 0.2),
    Record(0.1, Kind.VALUE, "flag", True),
    Record(0.2, Kind.VALUE, "level", math.nan),
    Record(0.2, Kind.VALUE, "level", -math.inf),
    Record(0.3, Kind.VALUE, "axis.state", "OPERATION_ENABLED"),
    Record(0.3, Kind.VALUE, "pixels", (1, 2.5, None)),
    Record(0.4, Kind.COMMAND, "valve", 40, "fill"),
    Record(0.4, Kind.CONFIRMED, "valve", 40),
    Record(0.5, Kind.COMMAND, "valve", 0.0, "safe:abnormal completion"),
    Record(0.6, Kind.STATUS, "level", "failed", "disconnected",
           'bus "plc": connection lost\nagain'),
    Record(1.0000004, Kind.EVENT, "fill", "abnormal", "", "fill: SensorFailure: -"),
    Record(1.5, Kind.BUS_ERROR, "plc", "exception-6", "level", "busy"),
)


def test_records_written_and_read_back_are_the_same(tmp_path: Path) -> None:
    trace = _trace(*RECORDS, system="tank", clock="virtual")
    lines = list(trace.lines())
    assert lines[:3] == ["# chcos-trace 1", "# system tank", "# clock virtual"]
    assert lines[3] == "0.100000 value level 0.30000000000000004"
    assert lines[7] == "0.300000 value axis.state \"OPERATION_ENABLED\""
    assert lines[8] == '0.300000 value pixels [1,2.5,null]'
    assert lines[9] == "0.400000 command valve 40 fill"
    assert lines[10] == "0.400000 confirmed valve 40"
    assert lines[11] == '0.500000 command valve 0.0 "safe:abnormal completion"'
    assert lines[13] == '1.000000 event fill "abnormal" - "fill: SensorFailure: -"'
    back = read_trace(trace.write(tmp_path / "run.trace"))
    assert back.header == {"system": "tank", "clock": "virtual"}
    assert back.entries == trace.entries
    assert [e.line for e in back.entries] == [e.line for e in trace.entries]
    assert back.entries[0].value == 0.30000000000000004
    assert math.isnan(back.entries[2].value) and back.entries[3].value == -math.inf
    assert back.entries[9].text == 'bus "plc": connection lost\nagain'
    assert back.entries[1].value is True and back.entries[6].value == 40
    assert isinstance(back.entries[7].value, int) and isinstance(back.entries[8].value, float)
    for e in trace.entries:
        assert parse_text(f"# chcos-trace 1\n{format_entry(e)}\n").entries == [e]


def test_a_gzip_trace_is_the_same_bytes_every_time(tmp_path: Path) -> None:
    trace = _trace(*RECORDS, system="tank")
    a = trace.write(tmp_path / "a.trace.gz").read_bytes()
    b = trace.write(tmp_path / "b.trace.gz").read_bytes()
    assert a == b and a[:2] == b"\x1f\x8b"
    assert read_trace(tmp_path / "a.trace.gz").entries == trace.entries


@pytest.mark.parametrize(("text", "error"), [
    ("", "empty: not a chcos trace"),
    ("hello\n", ":1: not a chcos trace"),
    ("# chcos-trace 1\nsoon value level 1\n", ":2: expected a time in seconds first"),
    ("# chcos-trace 1\n0.1 frobnicate level 1\n", ":2: unknown kind 'frobnicate'"),
    ("# chcos-trace 1\n0.1 value level\n", ":2: missing value"),
    ("# chcos-trace 1\n# x\n0.1 value level [1,\n", ":3: value: not JSON"),
    ("# chcos-trace 1\n0.1 status level \"OK\" - nope\n", ":2: the text must be a JSON string"),
])
def test_a_bad_trace_is_named_by_file_and_line(tmp_path: Path, text: str, error: str,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.trace"
    bad.write_text(text, encoding="utf-8")
    with pytest.raises(TraceError, match=f"{bad}{error}" if error.startswith(":") else error):
        read_trace(bad)
    good = _trace(*RECORDS).write(tmp_path / "good.trace")
    assert diff_main([str(good), str(bad)]) == 2
    assert str(bad) in capsys.readouterr().err


def test_values_are_signals_within_their_tolerance() -> None:
    golden = _trace(Record(0.1, Kind.VALUE, "level", 1.0), Record(0.2, Kind.VALUE, "level", 1.2))
    jitter = _trace(Record(0.1, Kind.VALUE, "level", 1.05),
                    Record(0.15, Kind.VALUE, "level", 1.08),
                    Record(0.2, Kind.VALUE, "level", 1.2))
    assert compare(golden, jitter, {"level": 0.1}).same
    assert compare(golden, jitter, {"*": 0.1}).same
    exact = compare(golden, jitter)
    assert not exact.same and exact.first is not None
    assert (exact.first.subject, exact.first.t, exact.first.what) == ("level", 0.1,
                                                                      "value held")
    assert "golden holds 1.0 (since t=0.100000 s), new holds 1.05" in exact.first.describe()
    late = _trace(Record(0.1, Kind.VALUE, "level", 1.0), Record(0.3, Kind.VALUE, "level", 1.2))
    d = compare(golden, late, {"level": 0.1}).first
    assert d is not None and d.t == 0.2 and d.golden is not None and d.golden.value == 1.2
    assert compare(golden, _trace(Record(0.1, Kind.VALUE, "level", math.nan)),
                   {"level": 1e9}).first is not None
    nan = _trace(Record(0.1, Kind.VALUE, "x", math.nan))
    assert compare(nan, nan).same


def test_everything_else_is_a_sequence() -> None:
    golden = _trace(Record(1.0, Kind.COMMAND, "valve", 40, "fill"),
                    Record(1.0, Kind.CONFIRMED, "valve", 40),
                    Record(2.0, Kind.STATUS, "level", "failed", "timeout", "port 5020"))
    same_but_text = _trace(Record(1.0, Kind.COMMAND, "valve", 40, "fill"),
                           Record(1.0, Kind.CONFIRMED, "valve", 40),
                           Record(2.0, Kind.STATUS, "level", "failed", "timeout", "port 5021"))
    assert compare(golden, same_but_text).same
    d = compare(golden, same_but_text, text=True).first
    assert d is not None and d.what == "text" and d.subject == "level"
    cases = {
        "time": _trace(Record(1.5, Kind.COMMAND, "valve", 40, "fill"),
                       Record(1.5, Kind.CONFIRMED, "valve", 40)),
        "cause": _trace(Record(1.0, Kind.COMMAND, "valve", 40, "host"),
                        Record(1.0, Kind.CONFIRMED, "valve", 40)),
        "value": _trace(Record(1.0, Kind.COMMAND, "valve", 41, "fill"),
                        Record(1.0, Kind.CONFIRMED, "valve", 41)),
        "missing in the new trace": _trace(Record(1.0, Kind.COMMAND, "valve", 40, "fill")),
    }
    for what, new in cases.items():
        result = compare(golden, new)
        first = result.first
        assert first is not None and first.subject == "valve" and first.what == what, what
        # the level's failure is missing from every one of them: its subject diverges too
        assert [d.subject for d in result.divergences] == ["valve", "level"]
    assert compare(golden, cases["value"], {"valve": 1}).divergences[0].subject == "level"
    extra = _trace(*RECORDS[:1])
    assert compare(_trace(), extra).first.what == "a value only one trace has"  # type: ignore


def test_tolerances_are_checked() -> None:
    assert parse_tolerances(["level=0.5", "*=1e-3"]) == {"level": 0.5, "*": 0.001}
    for bad in ("level", "level=-1", "=1", "level=nan", "level=lots"):
        with pytest.raises(ValueError, match="expected DEVICE=NUMBER"):
            parse_tolerances([bad])


def test_mcap_is_read_back_by_the_mcap_reader(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    trace = _trace(*RECORDS, system="tank")
    path = write_mcap(trace, tmp_path / "run.mcap")
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        got = [(ch.topic, msg.log_time, json.loads(msg.data))
               for _, ch, msg in reader.iter_messages(log_time_order=False)]
        summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == len(trace.entries)
    assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
    assert got[0] == ("/value/level", 100_000_000, {"t": 0.1, "value": 0.30000000000000004,
                                                     "cause": "", "text": ""})
    assert ("/command/valve", 400_000_000) in {(t, ns) for t, ns, _ in got}
    assert got[-1][0] == "/bus-error/plc" and got[-1][2]["value"] == "exception-6"


def test_an_event_names_the_task_it_concerns() -> None:
    tasks = ["fill", "A1", "C1"]
    assert event_subject("abnormal", "fill: SensorFailure: level", tasks) == "fill"
    assert event_subject("preempt", "C1 took A1 from fill (priority 3 > 2)", tasks) == "A1"
    assert event_subject("invoke", "host -> A1 at priority 4", tasks) == "A1"
    assert event_subject("estop", "E1: intruder", []) == "estop"
    assert entry_of(Record(0.123456789, Kind.EVENT, "A1", "restart")).t == 0.123457
