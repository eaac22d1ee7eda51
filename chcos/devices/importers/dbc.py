"""dbc - a device map for every signal of a CAN DBC (``chcos import dbc FILE``).

The DBC is read with cantools. Every signal of every message becomes a device addressed
``{message, signal}`` on one ``can`` bus that names the DBC; the ``can`` driver decodes and
encodes with the DBC's own scale and offset, so the device's ``scale`` stays 1 and the DBC's
factor and offset are noted in its comment. Units and limits (the signal's minimum and maximum)
come from the DBC. With ``node``, the messages that node sends become actuators (chcos plays that
node) and all others sensors; without it every signal is a sensor. A multiplexed message the node
sends is left out (named in the header): chcos does not send multiplexed messages. Sensors of
cyclic messages (``GenMsgCycleTime``) get ``stale_after`` = five cycles.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import MapDraft, limits
from chcos.errors import ConfigError


def import_dbc(path: str | Path, *, bus: str = "can0", node: str | None = None,
               machine: int = 0, prefix: str = "", dbc_ref: str | None = None,
               interface: str = "socketcan", channel: str = "can0") -> MapDraft:
    """The device-map draft of the DBC at ``path`` (see the module doc); ``dbc_ref`` is how the
    map names the DBC. Raises ConfigError naming the file if cantools cannot read it, or if
    ``node`` is not one of its nodes."""
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
    draft.buses.append({"name": bus, "kind": "can", "interface": interface, "channel": channel,
                        "dbc": dbc_ref or str(path)})
    names = [s.name for m in db.messages for s in m.signals]
    for msg in db.messages:
        actuator = node is not None and node in msg.senders
        if actuator and msg.is_multiplexed():
            draft.header.append(f"{msg.name} (0x{msg.frame_id:X}) is multiplexed: not imported "
                                f"(chcos decodes multiplexed messages for sensors but does not "
                                f"send them).")
            continue
        for sig in msg.signals:
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
            notes = [f"{msg.name} (0x{msg.frame_id:X}{ext}, from {senders}) {sig.name}: "
                     f"{sig.length} bit "
                     f"{'signed' if sig.is_signed else 'unsigned'}, raw * {sig.scale:g} + "
                     f"{sig.offset:g} (applied by the driver)"]
            if sig.choices:
                notes.append("values: " + ", ".join(f"{int(k)} {v}" for k, v in
                                                    sorted(sig.choices.items())))
            if sig.comment:
                notes.append(str(sig.comment))
            if not actuator and msg.cycle_time:
                dev["stale_after"] = round(5 * msg.cycle_time / 1000, 3)
                notes.append(f"cycle {msg.cycle_time} ms: stale after five cycles")
            if actuator:
                notes.append("set safe_value: written on e-stop, task failure and shutdown")
            draft.add(notes, dev)
    if not draft.devices:
        raise ConfigError(f"{path}: the DBC has no signals")
    return draft
