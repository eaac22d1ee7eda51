"""trace - the trace of a run: every device value and status change, every command handed to a
driver and confirmed (or failed), every bus error and task event, on the run's clock, as lines
of text that diff well (and, for viewers, as MCAP).

The text format (docs/hil-evidence.md, "The trace format")::

    # chcos-trace 1
    # system tank
    # clock virtual
    0.100000 value level 100.0
    0.100000 command valve 40 fill
    0.100000 confirmed valve 40
    1.100000 status level "failed" disconnected "modbus-tcp bus plc: connection to ... lost"
    1.100000 event fill "abnormal" - "fill: SensorFailure: ..."

One record per line, in the order the kernel saw them: the time (seconds since the start, six
decimals), the kind (:class:`chcos.hil.observe.Kind`), the subject (a device, a bus or a task),
the value (JSON: numbers as Python writes them, exactly; ``NaN``, ``Infinity``), the cause
class if there is one (a word, or a JSON string; ``-`` for none before a text) and, if there
is one, a text for people (a JSON
string: a failure's reason, an event's detail; ports and wall-clock figures in it differ between
runs, so :mod:`chcos.hil.diff` compares it only when asked). Lines starting with ``#`` are the
header. A file whose name ends in ``.gz`` is gzip-compressed (with no time stamp, so the same
run gives the same bytes).

:class:`TraceRecorder` is the :class:`chcos.hil.observe.Sink` that keeps a trace;
:func:`read_trace` reads a file (raising :class:`TraceError` naming the file and line);
:func:`write_mcap` writes MCAP (needs the ``mcap`` extra).
"""

from __future__ import annotations

import contextlib
import gzip
import io
import json
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from chcos.errors import ChcosError
from chcos.hil.observe import TRACE_KINDS, Kind, Record

FORMAT = "chcos-trace 1"
"""The first line of every trace file."""
_TOKEN = re.compile(r"[^\s\"]+")
_DECODER = json.JSONDecoder()


class TraceError(ChcosError):
    """A trace file that cannot be read or written (naming the file and, for a bad line, its
    number)."""


@dataclass(frozen=True, slots=True)
class Entry:
    """One line of a trace, as it reads back from the file (values as JSON gives them)."""

    t: float
    kind: str
    subject: str
    value: Any
    cause: str = ""
    text: str = ""
    line: int = field(default=0, compare=False)

    def describe(self) -> str:
        """The entry as a person reads it: ``t=1.100000 s status failed (disconnected)``."""
        cause = f" ({self.cause})" if self.cause else ""
        return f"t={self.t:.6f} s {self.kind} {_json(self.value)}{cause}"


@dataclass
class Trace:
    """A run's trace: its header (``system``, ``clock``...) and its entries in order."""

    header: dict[str, str] = field(default_factory=dict)
    entries: list[Entry] = field(default_factory=list)
    path: str = "<memory>"

    def subjects(self) -> list[str]:
        """Every subject, in the order it first appears."""
        return list(dict.fromkeys(e.subject for e in self.entries))

    def lines(self) -> Iterator[str]:
        """The trace as text lines (without line ends)."""
        yield f"# {FORMAT}"
        for key, value in self.header.items():
            yield f"# {key} {value}"
        for e in self.entries:
            yield format_entry(e)

    def write(self, path: str | Path) -> Path:
        """Write the trace to ``path`` (gzip for ``.gz``); returns it. Raises TraceError."""
        p = Path(path)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            with _open_write(p) as fh:
                for line in self.lines():
                    fh.write(line + "\n")
        except OSError as exc:
            raise TraceError(f"{p}: cannot write the trace: {exc}") from exc
        return p


def _plain(value: Any) -> Any:
    """A value JSON cannot carry as it is, as text (bytes, objects)."""
    if isinstance(value, bytes | bytearray):
        return value.hex()
    return repr(value)


def _json(value: Any) -> str:
    return json.dumps(value, separators=(",", ":"), default=_plain, ensure_ascii=False)


def _word(text: str) -> str:
    """``text`` as one field: itself if it is a word, else a JSON string; ``-`` if empty."""
    if not text:
        return "-"
    if text != "-" and _TOKEN.fullmatch(text):
        return text
    return _json(text)


def format_entry(e: Entry) -> str:
    """One trace line for ``e`` (see the module doc)."""
    line = f"{e.t:.6f} {e.kind} {_word(e.subject)} {_json(e.value)}"
    if e.text:
        return f"{line} {_word(e.cause)} {_json(e.text)}"
    return f"{line} {_word(e.cause)}" if e.cause else line


def entry_of(rec: Record, line: int = 0) -> Entry:
    """The entry ``rec`` becomes in a file (as line ``line``): the time to six decimals, the
    value as JSON reads it back (a tuple becomes a list), so an in-memory trace equals the one
    read from disk."""
    value = json.loads(_json(rec.value))
    return Entry(float(f"{rec.t:.6f}"), rec.kind.value, rec.subject, value, rec.cause, rec.text,
                 line)


class TraceRecorder:
    """The sink that keeps a run's trace (the records of :data:`TRACE_KINDS`), each entry with
    the line number it gets in the file."""

    def __init__(self, **header: str) -> None:
        self.trace = Trace(dict(header), path="this run")
        self._first_line = 2 + len(header)

    def record(self, rec: Record) -> None:
        """Keep ``rec`` if it belongs in a trace."""
        if rec.kind in TRACE_KINDS:
            entries = self.trace.entries
            entries.append(entry_of(rec, self._first_line + len(entries)))


# ---- reading ----------------------------------------------------------------------------------
def _field(line: str, pos: int, what: str) -> tuple[Any, int, bool]:
    """The field at ``pos`` (after spaces): (value, next position, whether it was JSON)."""
    while pos < len(line) and line[pos] == " ":
        pos += 1
    if pos >= len(line):
        raise ValueError(f"missing {what}")
    if what == "value" or line[pos] == '"':
        try:
            value, end = _DECODER.raw_decode(line, pos)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{what}: not JSON at column {pos + 1}: {exc.msg}") from None
        return value, end, True
    m = _TOKEN.match(line, pos)
    assert m is not None
    return m.group(0), m.end(), False


def parse_entry(line: str, number: int = 0) -> Entry:
    """One trace line; raises ValueError saying what is wrong with it."""
    t_text = line.partition(" ")[0]
    try:
        t = float(t_text)
    except ValueError:
        raise ValueError(f"expected a time in seconds first, got {t_text!r}") from None
    pos = len(t_text) + 1
    kind, pos, _ = _field(line, pos, "kind")
    if kind not in {k.value for k in Kind}:
        raise ValueError(f"unknown kind {kind!r} (expected one of "
                         f"{', '.join(sorted(k.value for k in TRACE_KINDS))})")
    subject, pos, _ = _field(line, pos, "subject")
    value, pos, _ = _field(line, pos, "value")
    cause, quoted = "", False
    if line[pos:].strip():
        cause, pos, quoted = _field(line, pos, "cause")
    if cause == "-" and not quoted:
        cause = ""
    text = ""
    if line[pos:].strip():
        text, pos, quoted = _field(line, pos, "text")
        if not quoted or not isinstance(text, str):
            raise ValueError("the text must be a JSON string")
        if line[pos:].strip():
            raise ValueError(f"unexpected {line[pos:].strip()[:20]!r} after the text")
    return Entry(t, str(kind), str(subject), value, str(cause), text, number)


def read_trace(path: str | Path) -> Trace:
    """Read a trace file (gzip for ``.gz``). Raises TraceError naming the file, and the line
    for a line that is not a trace line, if the file is missing, unreadable or not a trace."""
    p = Path(path)
    try:
        with _open_read(p) as fh:
            return _parse(fh, str(p))
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise TraceError(f"{p}: cannot read the trace: {exc}") from exc


def _parse(lines: Iterable[str], where: str) -> Trace:
    trace = Trace(path=where)
    first = True
    for number, raw in enumerate(lines, 1):
        line = raw.rstrip("\n")
        if first:
            if line.strip() != f"# {FORMAT}":
                raise TraceError(f"{where}:1: not a chcos trace: expected '# {FORMAT}', got "
                                 f"{line[:40]!r}")
            first = False
            continue
        if not line.strip():
            continue
        if line.startswith("#"):
            key, _, value = line[1:].strip().partition(" ")
            trace.header[key] = value
            continue
        try:
            trace.entries.append(parse_entry(line, number))
        except ValueError as exc:
            raise TraceError(f"{where}:{number}: {exc}") from None
    if first:
        raise TraceError(f"{where}: empty: not a chcos trace")
    return trace


def parse_text(text: str, where: str = "<text>") -> Trace:
    """A trace from its text. Raises TraceError as :func:`read_trace`."""
    return _parse(io.StringIO(text), where)


def _open_read(p: Path) -> IO[str]:
    if p.suffix == ".gz":
        return io.TextIOWrapper(gzip.open(p, "rb"), encoding="utf-8")
    return open(p, encoding="utf-8")


@contextlib.contextmanager
def _open_write(p: Path) -> Iterator[IO[str]]:
    if p.suffix == ".gz":
        with open(p, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw,
                                                 mtime=0) as gz, \
                io.TextIOWrapper(gz, encoding="utf-8") as fh:
            yield fh
    else:
        with open(p, "w", encoding="utf-8") as fh:
            yield fh


# ---- MCAP -------------------------------------------------------------------------------------
_MCAP_SCHEMA = {
    "type": "object", "title": "chcos trace record",
    "properties": {"value": {}, "cause": {"type": "string"}, "text": {"type": "string"},
                   "t": {"type": "number", "description": "seconds since the start"}},
}


def write_mcap(trace: Trace, path: str | Path) -> Path:
    """Write ``trace`` as MCAP (JSON messages, one channel per kind and subject:
    ``/value/level``, ``/status/level``, ``/command/valve``, ``/event/fill``...; log times are
    the run's clock in nanoseconds since the start), for viewers that read MCAP. Raises
    TraceError if the ``mcap`` package is not installed (``pip install 'chcos[mcap]'``) or the
    file cannot be written."""
    try:
        from mcap.writer import Writer
    except ImportError as exc:
        raise TraceError(f"{path}: writing MCAP needs the mcap package: pip install "
                         f"'chcos[mcap]' ({exc})") from exc
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        with open(p, "wb") as fh:
            writer = Writer(fh)
            writer.start(profile="", library="chcos")
            schema = writer.register_schema(name="chcos.trace.Record", encoding="jsonschema",
                                            data=json.dumps(_MCAP_SCHEMA).encode())
            channels: dict[tuple[str, str], int] = {}
            for seq, e in enumerate(trace.entries):
                topic = (e.kind, e.subject)
                if topic not in channels:
                    channels[topic] = writer.register_channel(
                        topic=f"/{e.kind}/{e.subject}", message_encoding="json",
                        schema_id=schema, metadata={"system": trace.header.get("system", "")})
                data = json.dumps({"t": e.t, "value": e.value, "cause": e.cause,
                                   "text": e.text}, default=_plain).encode()
                ns = round(e.t * 1e9)
                writer.add_message(channel_id=channels[topic], log_time=ns, publish_time=ns,
                                   data=data, sequence=seq)
            writer.finish()  # type: ignore[no-untyped-call]
    except OSError as exc:
        raise TraceError(f"{p}: cannot write the MCAP file: {exc}") from exc
    return p

