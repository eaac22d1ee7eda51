"""dbc - a device map for every signal of a CAN DBC (``chcos import dbc FILE``).

The DBC is scanned first (:mod:`.dbc_scan`: frame and signal sizes bounded before cantools
allocates anything), then read with cantools. Every signal of every message becomes a device
addressed ``{message, signal}`` on one ``can`` bus that names the DBC; the ``can`` driver decodes
and encodes with the DBC's own scale and offset, so the device's ``scale`` stays 1 and the DBC's
factor and offset are noted in its comment.

Who sends what: the messages chcos sends are those ``send`` names (shell patterns over message
names, ``--send``) and those ``node`` sends (``--node``, when the DBC has nodes); their signals
are actuators, every other signal a sensor. A multiplexed message chcos would send is left out
(named in the header and warned about): chcos does not send multiplexed messages.

Ranges: a device's ``limits`` are the DBC's minimum and maximum, clamped to what the signal can
carry (its raw bits x factor + offset) with a warning when they exceed it; limits that are not
finite or the wrong way round give the capacity, with a warning. An actuator always gets limits
(at least its capacity), so a write the frame cannot carry is refused at the device, never at the
encoder.

Freshness: a sensor of a cyclic message (``GenMsgCycleTime``) gets ``stale_after`` =
:data:`STALE_CYCLES` cycles (times the number of multiplexer values for a multiplexed signal,
which one frame in that many carries); a message without a cycle time gives no timeout and a
warning naming it.

Counters and checksums (:mod:`.dbc_computed`, by name and by layout) are declared on the bus as
``[[bus.message]]`` tables (``counter``, ``checksum = {signal, algorithm}``), so that the ``can``
driver computes them in the messages it sends and checks them in those it receives; they are not
devices in a message chcos sends. The checksum's algorithm cannot be read from a DBC: the likely
one is written, and the map's comment and a warning say it must be confirmed; ``checksums``
(``--checksum MESSAGE[.SIGNAL]=ALGORITHM``, ``python:module:callable`` for a function) sets it.

Every error names the file and the line (and the message or signal) where the DBC allows it.
"""

from __future__ import annotations

import fnmatch
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from chcos.devices.importers.dbc_computed import (
    ALGORITHMS,
    Computed,
    computed_signals,
    likely_algorithm,
)
from chcos.devices.importers.dbc_scan import DbcLines, locate, prescan
from chcos.devices.importers.draft import MapDraft, Table, clamp_limits
from chcos.errors import ConfigError

#: cycles of silence before a cyclic message's sensors are stale: a few frames lost in a row
#: (bus-off recovery, error frames under load) are tolerated, a sender that stopped is seen
#: within five of its periods
STALE_CYCLES = 5
#: the longest cycle time taken from a DBC (ms); a larger one is a typo or a placeholder
MAX_CYCLE_MS = 3_600_000


def _picked(patterns: Sequence[str], message: str, signal: str) -> bool:
    return not patterns or any(fnmatch.fnmatchcase(signal, p)
                               or fnmatch.fnmatchcase(f"{message}.{signal}", p)
                               for p in patterns)


def _load(path: Path) -> tuple[Any, DbcLines]:
    """cantools' database of the DBC at ``path`` and where its declarations are; raises
    ConfigError naming the file and, where it can, the line."""
    import cantools

    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the DBC: {exc.strerror or exc}") from exc
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("cp1252", errors="replace")   # cantools' own default encoding
    lines = prescan(path, text)
    try:
        db = cantools.database.load_string(text, database_format="dbc", strict=True)
    except Exception as exc:  # cantools' parse and consistency errors, of every kind
        full = str(exc).replace("\n", " ")
        detail = full[:300] or type(exc).__name__
        where = "" if re.search(r"line \d+", detail) else (locate(lines, full, text) or "")
        if not where and "list index out of range" in full:
            # cantools' tokenizer ran past the last token: the file ends inside a statement
            where = f"line {len(text.splitlines())} (the file ends inside a statement)"
        raise ConfigError(f"{path}: " + (f"{where}: " if where else "")
                          + f"not a readable DBC: {detail}") from exc
    return db, lines


def parse_checksums(items: Sequence[str]) -> dict[str, dict[str, str]]:
    """``--checksum MESSAGE[.SIGNAL]=ALGORITHM`` items as {message: {signal?, algorithm,
    function?}}; raises ConfigError naming the item."""
    out: dict[str, dict[str, str]] = {}
    for item in items:
        target, eq, algo = item.partition("=")
        message, _dot, signal = target.strip().partition(".")
        algo = algo.strip()
        spec: dict[str, str] = {}
        if algo.startswith("python:"):
            function = algo[len("python:"):]
            module, colon, func = function.partition(":")
            if not colon or not module or not func.isidentifier():
                raise ConfigError(f"--checksum {item!r}: expected python:module:function")
            spec = {"algorithm": "python", "function": function}
        elif algo in ALGORITHMS and algo != "python":
            spec = {"algorithm": algo}
        if not eq or not message or not spec:
            fixed = ", ".join(a for a in ALGORITHMS if a != "python")
            raise ConfigError(f"--checksum {item!r}: expected MESSAGE[.SIGNAL]=ALGORITHM, "
                              f"ALGORITHM one of {fixed} or python:module:function")
        if signal:
            spec["signal"] = signal
        out[message] = spec
    return out


def capacity(sig: Any) -> tuple[float, float]:
    """What ``sig`` can carry in engineering units: its raw range x factor + offset."""
    if sig.is_float:
        top = 3.4028234663852886e38 if sig.length == 32 else 1.7976931348623157e308
        raw = (-top, top)
    elif sig.is_signed:
        raw = (-(2.0 ** (sig.length - 1)), 2.0 ** (sig.length - 1) - 1)
    else:
        raw = (0.0, 2.0 ** sig.length - 1)
    ends = [r * sig.scale + sig.offset for r in raw]
    return min(ends), max(ends)


def _branches(msg: Any) -> int:
    """How many multiplexer values the multiplexed signals of ``msg`` are spread over."""
    ids = {i for s in msg.signals for i in (s.multiplexer_ids or ())}
    return max(1, len(ids))


def _cycle(msg: Any, warnings: list[str], where: str) -> float | None:
    """The message's cycle time in seconds (None: event-driven or not given)."""
    cycle = msg.cycle_time
    if not cycle:
        return None
    if not isinstance(cycle, int | float) or not 0 < cycle <= MAX_CYCLE_MS:
        warnings.append(f"{where}: {msg.name}: GenMsgCycleTime {cycle!r} ms is not a cycle "
                        f"(expected 1..{MAX_CYCLE_MS}): taken as none")
        return None
    return float(cycle) / 1000


class _Senders:
    """Which messages chcos sends: those of ``--send`` and of ``--node``."""

    def __init__(self, db: Any, path: Path, node: str | None, send: Sequence[str]) -> None:
        nodes = [n.name for n in db.nodes]
        if node is not None and node not in nodes:
            known = ", ".join(nodes) or "none: name the messages chcos sends with --send"
            raise ConfigError(f"{path}: --node {node!r}: expected one of the DBC's nodes "
                              f"({known})")
        names = [m.name for m in db.messages]
        self.patterns = list(send)
        for pattern in send:
            if not any(fnmatch.fnmatchcase(n, pattern) for n in names):
                raise ConfigError(f"{path}: --send {pattern!r}: no such message (the DBC's: "
                                  f"{', '.join(names[:20])}{', ...' if len(names) > 20 else ''})")
        self.node = node

    def sends(self, msg: Any) -> bool:
        return (self.node is not None and self.node in msg.senders) or any(
            fnmatch.fnmatchcase(msg.name, p) for p in self.patterns)


def import_dbc(path: str | Path, *, bus: str = "can0", node: str | None = None,
               machine: int = 0, prefix: str = "", dbc_ref: str | None = None,
               interface: str = "socketcan", channel: str = "can0",
               signals: Sequence[str] = (), udp_port: int | None = None,
               send: Sequence[str] = (),
               checksums: Mapping[str, Mapping[str, str]] | None = None) -> MapDraft:
    """The device-map draft of the DBC at ``path`` (see the module doc); ``dbc_ref`` is how the
    map names the DBC; ``signals``: shell-style patterns of the signals to import (all if
    empty); ``send``: patterns of the messages chcos sends; ``checksums``: from
    :func:`parse_checksums`. Raises ConfigError naming the file (and line where it can) if the
    DBC cannot be read, ``node`` is not one of its nodes, a ``send`` pattern or checksum
    message matches no message, or nothing is left to import. ``udp_port``: the bus's ``port``
    (the ``udp_multicast`` interface only)."""
    path = Path(path)
    db, lines = _load(path)
    senders = _Senders(db, path, node, send)
    chosen = dict(checksums or {})
    for message in chosen:
        if message not in {m.name for m in db.messages}:
            raise ConfigError(f"{path}: --checksum {message}: no such message in the DBC")
    draft = MapDraft()
    draft.header = [f"CAN bus from {path.name} ({len(db.messages)} messages), imported by "
                    "chcos import dbc" + (f" as node {node}" if node else "")
                    + (f", sending {' '.join(send)}" if send else "") + ".",
                    "Check with chcos check; set safe_value on the actuators.",
                    "Delete interface/channel to take them from python-can's configuration."]
    bus_table: dict[str, Any] = {"name": bus, "kind": "can", "interface": interface,
                                 "channel": channel}
    if udp_port is not None:
        if interface != "udp_multicast":
            raise ConfigError(f"--udp-port {udp_port}: only with --interface udp_multicast")
        bus_table["port"] = udp_port
    bus_table["dbc"] = dbc_ref or str(path)
    draft.buses.append(bus_table)
    names = [s.name for m in db.messages for s in m.signals]
    counts: dict[str, int] = {}
    for n in names:
        counts[n] = counts.get(n, 0) + 1
    tables: list[Table] = []
    silent: list[str] = []
    for msg in db.messages:
        where = f"{path}: line {lines.messages.get(msg.name, '?')}"
        before = len(draft.devices)
        _message_devices(msg, senders.sends(msg), draft, counts, signals,
                         bus=bus, machine=machine, prefix=prefix, where=where, silent=silent)
        if len(draft.devices) > before:   # a message no device uses needs no table
            table = _message_table(msg, senders.sends(msg), chosen.get(msg.name), draft,
                                   where, path)
            if table is not None:
                tables.append(table)
    if tables:
        bus_table["message"] = tables
    if silent:
        draft.warnings.append(
            f"{path}: no cycle time (GenMsgCycleTime) for {', '.join(silent[:12])}"
            + (f" and {len(silent) - 12} more" if len(silent) > 12 else "")
            + ": their sensors get no stale_after, so a sender that stops goes unnoticed; "
              "if they are cyclic, set stale_after to a few of their periods")
    if not draft.devices:
        raise ConfigError(f"{path}: no signals to import"
                          + (f" (--signals {' '.join(signals)} matched none)" if signals
                             else " (no SG_ line the importer can use)"))
    return draft


def _message_table(msg: Any, sent: bool, chosen: Mapping[str, str] | None, draft: MapDraft,
                   where: str, path: Path) -> Table | None:
    """The ``[[bus.message]]`` table declaring ``msg``'s counter and checksum (None: it has
    neither), with the comments and warnings saying what was guessed."""
    found = {c.kind: c for c in computed_signals(msg)}
    if chosen is not None and "signal" in chosen:
        if chosen["signal"] not in [s.name for s in msg.signals]:
            raise ConfigError(f"{path}: --checksum {msg.name}.{chosen['signal']}: no such "
                              f"signal in {msg.name}")
        found["checksum"] = Computed(chosen["signal"], "checksum", "named by --checksum")
    if not found or (sent and msg.is_multiplexed()):
        return None
    values: dict[str, Any] = {"name": msg.name}
    does = "chcos sends it: the driver computes" if sent else \
        "chcos receives it: the driver checks"
    comments = [f"{msg.name} (0x{msg.frame_id:X}): {does} "
                + " and ".join(f"the {c.kind} {c.signal} (found {c.how})"
                               for c in found.values())]
    if "counter" in found:
        values["counter"] = found["counter"].signal
    if "checksum" in found:
        signal = found["checksum"].signal
        spec: dict[str, str] = {"signal": signal}
        if chosen is not None:
            spec["algorithm"] = chosen["algorithm"]
            if "function" in chosen:
                spec["function"] = chosen["function"]
            comments.append(f"checksum algorithm {chosen['algorithm']}: given with --checksum")
        else:
            spec["algorithm"] = likely_algorithm(msg, signal)
            comments.append(f"checksum algorithm {spec['algorithm']}: a GUESS (a DBC does not "
                            "say it): confirm it with the ECU's documentation, or a receiver "
                            "drops every frame")
            draft.warnings.append(
                f"{where}: {msg.name}: checksum {signal}: algorithm {spec['algorithm']} is a "
                f"guess, the DBC does not say: confirm it (--checksum {msg.name}=ALGORITHM, "
                f"one of {', '.join(ALGORITHMS[:-1])} or python:module:function)")
        values["checksum"] = spec
    return Table(comments, values)


def _message_devices(msg: Any, sent: bool, draft: MapDraft, counts: Mapping[str, int],
                     patterns: Sequence[str], *, bus: str, machine: int, prefix: str,
                     where: str, silent: list[str]) -> None:
    """The devices of ``msg``'s signals (see the module doc)."""
    if sent and msg.is_multiplexed():
        draft.header.append(f"{msg.name} (0x{msg.frame_id:X}) is multiplexed: not imported "
                            "(chcos decodes multiplexed messages for sensors but does not "
                            "send them).")
        draft.warnings.append(f"{where}: {msg.name} is multiplexed: chcos does not send "
                              "multiplexed messages; left out of the map")
        return
    computed = {c.signal: c for c in computed_signals(msg)}
    cycle = _cycle(msg, draft.warnings, where)
    picked = [s for s in msg.signals if _picked(patterns, msg.name, s.name)]
    if not sent and cycle is None and picked:
        silent.append(msg.name)
    for sig in picked:
        if sent and sig.name in computed:
            continue      # the driver computes it (the message's [[bus.message]] table)
        _signal_device(msg, sig, sent, draft, counts, computed.get(sig.name), cycle, bus=bus,
                       machine=machine, prefix=prefix, where=where)


def _signal_device(msg: Any, sig: Any, sent: bool, draft: MapDraft, counts: Mapping[str, int],
                   computed: Computed | None, cycle: float | None, *, bus: str, machine: int,
                   prefix: str, where: str) -> None:
    """One signal's device, with its comment lines."""
    if sig.scale == 0 or not all(map(math.isfinite, (sig.scale, sig.offset))):
        draft.warnings.append(f"{where}: {msg.name}.{sig.name}: factor {sig.scale!r}, offset "
                              f"{sig.offset!r}: no value can be coded; left out of the map")
        return
    base = sig.name if counts.get(sig.name, 0) == 1 else f"{msg.name}_{sig.name}"
    dev: dict[str, Any] = {
        "name": draft.name(base, prefix),
        "direction": "actuator" if sent else "sensor", "machine": machine,
        "bus": bus, "address": {"message": msg.name, "signal": sig.name}}
    lim = clamp_limits(sig.minimum, sig.maximum, capacity(sig),
                       f"{where}: {msg.name}.{sig.name}", draft.warnings)
    if lim is not None and (sent or sig.minimum is not None or sig.maximum is not None):
        dev["limits"] = lim
    if sig.unit:
        dev["units"] = str(sig.unit)
    ext = ", extended" if msg.is_extended_frame else ""
    senders = ", ".join(msg.senders) or "?"
    kind = ("float" if sig.is_float else "signed" if sig.is_signed else "unsigned")
    notes = [f"{msg.name} (0x{msg.frame_id:X}{ext}, from {senders}) {sig.name}: "
             f"{sig.length} bit {kind}, raw * {sig.scale:g} + {sig.offset:g} "
             "(applied by the driver)"]
    if sig.is_multiplexer:
        notes.append("the message's multiplexer: which of its multiplexed signals a frame "
                     "carries")
    if sig.multiplexer_ids:
        notes.append(f"multiplexed: carried when {sig.multiplexer_signal} = "
                     + " or ".join(str(i) for i in sig.multiplexer_ids))
    if sig.choices:
        notes.append("values: " + ", ".join(f"{int(k)} {v}" for k, v in
                                            sorted(sig.choices.items())))
    if sig.comment:
        notes.append(str(sig.comment))
    if computed is not None:
        notes.append(f"a {'rolling counter' if computed.kind == 'counter' else 'checksum'} "
                     "the sender computes per frame: read it, do not expect a steady value "
                     "(the driver checks it: the bus's message table)")
    if not sent and cycle is not None:
        spread = _branches(msg) if sig.multiplexer_ids else 1
        dev["stale_after"] = round(STALE_CYCLES * spread * cycle, 6)
        notes.append(f"cycle {cycle * 1000:g} ms: stale after {STALE_CYCLES} cycles"
                     + (f" of each of its {spread} multiplexer values" if spread > 1 else ""))
    if sent:
        notes.append("set safe_value: written on e-stop, task failure and shutdown")
    draft.add(notes, dev)
