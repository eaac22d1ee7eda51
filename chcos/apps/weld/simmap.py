"""simmap - where the simulated welding cell listens, and the device map that reaches it.

:mod:`chcos.apps.weld.plant` serves the cell on :data:`DEFAULT_CANOPEN_CHANNEL`,
:data:`DEFAULT_SENSOR_CHANNEL`, :data:`DEFAULT_MODBUS_PORT` and :data:`DEFAULT_SERIAL_PORT`
unless told otherwise; ``chcos/apps/weld/maps/weld_cell.toml`` (:data:`CELL_TOML`) is the
controller's side at those defaults, and :func:`cell_devmap` writes a copy bound to other
channels and ports (tests and ``chcos run --binding buses`` use fresh ones per run).
"""

from __future__ import annotations

import re
from pathlib import Path

from chcos.apps.weld.slaves import BUSCONFIG, NODE_IDS, WELD_DBC, WELD_EDS
from chcos.errors import ConfigError
from chcos.helpers import is_int

DEFAULT_CANOPEN_CHANNEL = "weld-canopen"
DEFAULT_SENSOR_CHANNEL = "weld-sensors"
DEFAULT_MODBUS_PORT = 15020
DEFAULT_SERIAL_PORT = 15021

#: The cell's device map (fixed default channels and ports).
CELL_TOML = BUSCONFIG / "weld_cell.toml"


def cell_devmap(dest_dir: str | Path, *, canopen_channel: str, sensor_channel: str,
                modbus_port: int, serial_port: int, interface: str = "virtual") -> Path:
    """Write ``weld_cell.toml`` into ``dest_dir`` bound to these CAN channels (python-can
    ``interface``), Modbus port and serial port on 127.0.0.1, with the EDS and DBC paths made
    absolute; returns the new file's path. Raises ConfigError for bad arguments or a template
    that no longer has the lines to rebind (naming the file and the line expected)."""
    for what, chan in (("canopen_channel", canopen_channel), ("sensor_channel", sensor_channel),
                       ("interface", interface)):
        if not (isinstance(chan, str) and chan and '"' not in chan and "\\" not in chan):
            raise ConfigError(f"cell_devmap {what}={chan!r}: expected a non-empty name without "
                              f"quotes or backslashes")
    for what, port in (("modbus_port", modbus_port), ("serial_port", serial_port)):
        if not (is_int(port) and 1 <= port <= 65535):
            raise ConfigError(f"cell_devmap {what}={port!r}: expected a TCP port 1..65535")
    text = CELL_TOML.read_text(encoding="utf-8")
    rebind = [
        ('interface = "virtual"', f'interface = "{interface}"', 2),
        (f'channel = "{DEFAULT_CANOPEN_CHANNEL}"', f'channel = "{canopen_channel}"', 1),
        (f'channel = "{DEFAULT_SENSOR_CHANNEL}"', f'channel = "{sensor_channel}"', 1),
        (f"port = {DEFAULT_MODBUS_PORT}", f"port = {modbus_port}", 1),
        (f'url = "socket://127.0.0.1:{DEFAULT_SERIAL_PORT}"',
         f'url = "socket://127.0.0.1:{serial_port}"', 1),
        ('eds = "weld_servo.eds"', f'eds = "{WELD_EDS.as_posix()}"', len(NODE_IDS)),
        ('dbc = "weld_cell.dbc"', f'dbc = "{WELD_DBC.as_posix()}"', 1),
    ]
    for old, new, count in rebind:
        pattern = re.compile(r"(?<![\w.])" + re.escape(old) + r"(?![\w.])")
        text, found = pattern.subn(new, text)
        if found != count:
            raise ConfigError(f"{CELL_TOML}: expected {count} line(s) with {old!r} to rebind, "
                              f"found {found}")
    dest = Path(dest_dir)
    try:
        dest.mkdir(parents=True, exist_ok=True)
        out = dest / CELL_TOML.name
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cell_devmap: cannot write into {dest}: {exc}") from exc
    return out
