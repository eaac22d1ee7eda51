"""dbc - a device map for every signal of a CAN DBC (``chcos import dbc FILE``).

The DBC is read with cantools. Every signal of every message becomes a device addressed
``{message, signal}`` on one ``can`` bus that names the DBC; the ``can`` driver decodes and
encodes with the DBC's own scale and offset, so the device's ``scale`` stays 1 and the DBC's
factor and offset are noted in its comment. Units and limits (the signal's minimum and maximum)
come from the DBC. With ``node``, the messages that node sends become actuators (chcos plays that
node) and all others sensors; without it every signal is a sensor. A multiplexed message the node
sends is left out (named in the header): chcos does not send multiplexed messages. Sensors of
cyclic messages (``GenMsgCycleTime``) get ``stale_after`` = five cycles.

What the DBC says that the map cannot: a multi-line comment becomes one comment line each; a
multiplexed signal is imported with its multiplexer and the multiplexer values it is sent with
noted; a rolling counter or a CRC/checksum (by its name: ``counter``, ``alive``, ``crc``,
``checksum``...) in a message chcos sends is left out of the map with a comment and a warning
(the driver does not compute them: a receiver that checks them drops every frame), while in a
message chcos receives it stays a sensor, noted as such. ``signals`` picks signals by
shell-style patterns over ``SIGNAL`` or ``MESSAGE.SIGNAL``.
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import MapDraft, limits
from chcos.errors import ConfigError

#: signal names of rolling counters and checksums, which the sending node computes per frame
COMPUTED = re.compile(r"(?i)(counter|cntr|\bcnt|_cnt|cnt_|alive|rolling|crc|checksum|chksum|"
                      r"chks|parity)")


def computed_kind(signal: str) -> str | None:
    """``"rolling counter"`` or ``"checksum"`` if ``signal``'s name says it is one, else None."""
    m = COMPUTED.search(signal)
    if m is None:
        return None
    word = m.group(1).lower()
    return "checksum" if word in ("crc", "checksum", "chksum", "chks", "parity") \
        else "rolling counter"


def _picked(patterns: Sequence[str], message: str, signal: str) -> bool:
    return not patterns or any(fnmatch.fnmatchcase(signal, p)
                               or fnmatch.fnmatchcase(f"{message}.{signal}", p)
                               for p in patterns)


def import_dbc(path: str | Path, *, bus: str = "can0", node: str | None = None,
               machine: int = 0, prefix: str = "", dbc_ref: str | None = None,
               interface: str = "socketcan", channel: str = "can0",
               signals: Sequence[str] = (), udp_port: int | None = None) -> MapDraft:
    """The device-map draft of the DBC at ``path`` (see the module doc); ``dbc_ref`` is how the
    map names the DBC; ``signals``: shell-style patterns of the signals to import (all if
    empty). Raises ConfigError naming the file if cantools cannot read it, if ``node`` is not
    one of its nodes, or if nothing is left to import. ``udp_port``: the bus's ``port`` (the
    ``udp_multicast`` interface only)."""
    import cantools

    try:
        db: Any = cantools.database.load_file(str(path), database_format="dbc")
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: cannot read the DBC: {exc}") from exc
    except Exception as exc:  # cantools' parse errors
        raise ConfigError(f"{path}: not a readable DBC: {exc}") from exc
    nodes = [n.name for n in db.nodes]
    if node is not None and node not in nodes:
        raise ConfigError(f"{path}: --node {node!r}: expected one of the DBC's nodes "
                          f"({', '.join(nodes) or 'none'})")
    draft = MapDraft()
    draft.header = [f"CAN bus from {Path(path).name} ({len(db.messages)} messages), imported by "
                    "chcos import dbc" + (f" as node {node}" if node else "") + ".",
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
    for msg in db.messages:
        actuator = node is not None and node in msg.senders
        if actuator and msg.is_multiplexed():
            draft.header.append(f"{msg.name} (0x{msg.frame_id:X}) is multiplexed: not imported "
                                f"(chcos decodes multiplexed messages for sensors but does not "
                                f"send them).")
            continue
        left_out: list[str] = []
        for sig in msg.signals:
            if not _picked(signals, msg.name, sig.name):
                continue
            computed = computed_kind(sig.name)
            if actuator and computed is not None:
                left_out.append(f"{sig.name} ({computed})")
                continue
            base = sig.name if names.count(sig.name) == 1 else f"{msg.name}_{sig.name}"
            dev: dict[str, Any] = {
                "name": draft.name(base, prefix),
                "direction": "actuator" if actuator else "sensor", "machine": machine,
                "bus": bus, "address": {"message": msg.name, "signal": sig.name}}
            lim = limits(sig.minimum, sig.maximum)
            if lim is not None:
                dev["limits"] = lim
            if sig.unit:
                dev["units"] = sig.unit
            ext = ", extended" if msg.is_extended_frame else ""
            senders = ", ".join(msg.senders) or "?"
            kind = ("float" if sig.is_float else "signed" if sig.is_signed else "unsigned")
            notes = [f"{msg.name} (0x{msg.frame_id:X}{ext}, from {senders}) {sig.name}: "
                     f"{sig.length} bit {kind}, raw * {sig.scale:g} + {sig.offset:g} "
                     "(applied by the driver)"]
            if sig.is_multiplexer:
                notes.append("the message's multiplexer: which of its multiplexed signals a "
                             "frame carries")
            if sig.multiplexer_ids:
                notes.append(f"multiplexed: carried when {sig.multiplexer_signal} = "
                             + " or ".join(str(i) for i in sig.multiplexer_ids))
            if sig.choices:
                notes.append("values: " + ", ".join(f"{int(k)} {v}" for k, v in
                                                    sorted(sig.choices.items())))
            if sig.comment:
                notes.append(str(sig.comment))
            if computed is not None:
                notes.append(f"a {computed} the sender computes per frame: read it, do not "
                             "expect a steady value")
            if not actuator and msg.cycle_time:
                dev["stale_after"] = round(5 * msg.cycle_time / 1000, 3)
                notes.append(f"cycle {msg.cycle_time} ms: stale after five cycles")
            if actuator:
                notes.append("set safe_value: written on e-stop, task failure and shutdown")
            draft.add(notes, dev)
        if left_out:
            what = ", ".join(left_out)
            draft.header.append(f"Left out of {msg.name} (0x{msg.frame_id:X}): {what}: the "
                                "sending node computes them per frame and the can driver "
                                "does not; it sends their initial value.")
            draft.warnings.append(
                f"{path}: {msg.name} (0x{msg.frame_id:X}) carries {what}, left out of the map: "
                "chcos sends the initial value in every frame, so a receiver that checks them "
                "will drop the frames on a real bus")
    if not draft.devices:
        raise ConfigError(f"{path}: no signals to import"
                          + (f" (--signals {' '.join(signals)} matched none)" if signals
                             else ""))
    return draft
