"""scaffold - ``chcos new DIR``: a new cell project a user starts from.

Writes a system file, a device map (one Modbus TCP PLC with one sensor and one actuator), one task,
an install script, a README and a test that runs the cell on virtual time against a simulated PLC
through the ``chcos.testing`` pytest plugin, so that ``cd DIR && pytest`` passes at once and
``chcos run system.toml --outputs on`` runs the cell against the real PLC.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from chcos.errors import ConfigError

SYSTEM = """\
# The system file of cell {name}: what `chcos run system.toml` runs.
# Every key is described in the chcos README ("System files").
[system]
name = "{name}"
devmaps = ["devices.toml"]   # device maps, relative to this file
task_path = ["tasks"]        # where task code is found: task `fill` is tasks/fill.py
install = "install.chcos"    # host commands run before the clock starts
"""

DEVICES = """\
# Device map of cell {name}: one Modbus TCP PLC with a level sensor and a valve.
# Check it with `chcos check devices.toml`; every key is in the chcos device-map reference.

[[bus]]
name = "plc"
kind = "modbus-tcp"
host = "{host}"
port = {port}
poll_period = 0.1        # seconds between polls of the sensors
# If chcos is killed (SIGKILL, power cut of this computer) nothing writes the valve any more and
# the PLC keeps its last value: the protection is the PLC's own comm-loss watchdog. chcos
# writes this register every second (1, 2, 3 ...); program the PLC to close the valve when it
# stops changing for 3 s (docs/modbus-faults.md, "The watchdog register"). Uncomment:
# watchdog = {{ unit = 1, table = "holding", address = 900, period = 1.0, value = "counter" }}

[[device]]
name = "level"
direction = "sensor"
machine = 0
bus = "plc"
address = {{ unit = 1, table = "input", address = 0, type = "uint16" }}
scale = 0.1              # register 425 -> 42.5 cm
units = "cm"
limits = [0.0, 200.0]
stale_after = 1.0        # no answer for 1 s: the sensor is stale and its reader is told

[[device]]
name = "valve"
direction = "actuator"
machine = 0
bus = "plc"
address = {{ unit = 1, table = "holding", address = 1, type = "uint16" }}
units = "%"
limits = [0.0, 100.0]    # commands outside are refused, never clamped
safe_value = 0.0         # written on Ctrl-C, on e-stop and when the task fails; NOT after a
                         # SIGKILL of chcos: then only the PLC's watchdog (bus above) helps
"""

TASK = '''\
"""fill - keeps the tank level at its set-point by opening the inlet valve.

Invoked with ``invoke fill setpoint=120`` (cm). Reads sensor ``level``, writes actuator ``valve``
(0..100 %), proportionally to how far the level is below the set-point.
"""

from typing import Any

from chcos.user.context import TaskContext

GAIN = 2.0  # % of valve opening per cm below the set-point


async def main(ctx: TaskContext, command: Any) -> None:
    setpoint = float((command or {{}}).get("setpoint", 100.0))
    while True:
        level = await ctx.read("level")          # waits for the next reading
        opening = max(0.0, min(100.0, GAIN * (setpoint - level)))
        ctx.write("valve", round(opening))
'''

INSTALL = """\
# Host commands that build cell {name} (chcos README: "Host commands").
install -m0 sysfile                    # machine 0: start the drivers of its devices
# task fill: input level, output valve. --standing --restart=on-recovery: when the PLC drops
# out, fill ends abnormally and the valve goes to its safe value; once the level reads again,
# fill is invoked again with its last command (after --backoff seconds), so the cell rides
# through a network blip instead of staying safe until someone notices (see README.md).
install -m0i1o1 --standing --restart=on-recovery --backoff=0.5 fill level valve
invoke fill setpoint=120               # start it with its command
"""

TEST = '''\
"""Tests of cell {name}: the cell on virtual time against a simulated PLC built from
devices.toml (the chcos.testing pytest plugin gives the `chcos_cell` fixture)."""


def test_valve_opens_below_the_setpoint(chcos_cell):
    cell = chcos_cell("system.toml")
    cell.set("level", 100.0)                 # the simulated PLC's input register 0 = 1000
    cell.run_for(1.0)
    assert cell.value("level") == 100.0
    assert cell.peer("valve") == 40          # 2 % per cm, 20 cm below 120: in the PLC's register
    cell.set("level", 130.0)
    cell.run_for(1.0)
    assert cell.peer("valve") == 0


def test_a_failed_sensor_makes_the_valve_safe(chcos_cell):
    cell = chcos_cell("system.toml")
    cell.set("level", 90.0)
    cell.run_for(1.0)
    assert cell.peer("valve") == 60
    cell.fail("level", "float switch broken")  # fault: the sensor fails
    cell.run_for(0.5)
    assert cell.task("fill").abnormal == 1   # the task was told and ended abnormally
    assert cell.peer("valve") == 0           # its actuator's safe value reached the PLC
    cell.recover("level")                    # the fault ends (a reading alone would not)
    cell.run_for(1.0)                        # restart on recovery: fill runs again by itself
    assert cell.status("level") == "OK"
    assert cell.peer("valve") == 60
    cell.invoke("fill", setpoint=100)        # a new command from the host
    cell.run_for(1.0)
    assert cell.peer("valve") == 20


def test_the_cell_rides_through_a_plc_blip(chcos_cell):
    cell = chcos_cell("system.toml")
    cell.set("level", 90.0)
    cell.run_for(1.0)
    assert cell.peer("valve") == 60
    cell.silence("plc")                      # the PLC drops off the network for 2 s
    cell.run_for(2.0)
    assert cell.status("level") != "OK"      # stale: the task was told and stopped
    cell.restore("plc")                      # it is back: the driver finds it at its next retry
    cell.run_until(lambda: cell.status("level") == "OK")
    cell.run_for(1.0)
    assert cell.task("fill").abnormal >= 1
    assert cell.peer("valve") == 60          # fill restarted on recovery: controlling again
'''

README = """\
# Cell {name}

A chcos cell: one Modbus TCP PLC at {host}:{port} with a level sensor (input register 0, 0.1 cm
per count) and an inlet valve (holding register 1, 0..100 %), and one task, `fill`, that opens
the valve in proportion to how far the level is below its set-point.

| file | what it is |
|---|---|
| `system.toml` | the system file: device maps, task path, install script |
| `devices.toml` | the device map: the PLC's bus and the two devices |
| `tasks/fill.py` | the task |
| `install.chcos` | host commands run at start: load machine 0, install and invoke `fill` |
| `tests/test_cell.py` | tests on virtual time against a simulated PLC (`pytest`) |
| `chcos-{name}.service` | systemd unit: at boot, outputs on, restarted on a crash, `{name}.log` |

`fill` is installed `--standing --restart=on-recovery`. Without a restart policy a task that ends
abnormally stays ended (the thesis' rule: its owner decides): after the PLC's first network blip
the valve would sit at its safe value until someone invoked `fill` again. With it, the valve goes
safe while the level cannot be read, and `fill` is invoked again with its last command half a
second after the level reads again; `tests/test_cell.py` shows both (a failed sensor, a 2 s PLC
blip).

```sh
chcos check devices.toml                     # validate the device map
pytest                                       # the tests, no hardware needed
pytest --chcos-coverage -v                   # which device states the tests reached
chcos run system.toml --virtual --duration 5 # the cell against a simulated PLC
chcos run system.toml                        # the real PLC: tasks run, the valve is not driven
chcos run system.toml --outputs on           # the real PLC, driven; Ctrl-C: the valve goes to 0
```
"""

UNIT = """\
# systemd unit of cell {name}: runs it at boot and again after a crash. Install it with
#   sudo cp chcos-{name}.service /etc/systemd/system/ && sudo systemctl enable --now chcos-{name}
# Stopping it (systemctl stop, shutdown) sends SIGTERM: every actuator goes to its safe value.
[Unit]
Description=chcos cell {name}
Wants=network-online.target
After=network-online.target

[Service]
Type=simple
WorkingDirectory={workdir}
ExecStart={python} -m chcos.cli.main run system.toml --outputs on --log {name}.log
Restart=on-failure
RestartSec=5
TimeoutStopSec=30

[Install]
WantedBy=multi-user.target
"""


def create(directory: str | Path, *, name: str | None = None, host: str = "127.0.0.1",
           port: int = 5020) -> list[Path]:
    """Write a new cell project into ``directory`` (created; it must be empty or absent);
    returns the files written. Raises ConfigError if the directory is not empty, or the name is
    not letters, digits, - and _."""
    root = Path(directory)
    name = name or root.resolve().name
    if not re.fullmatch(r"[A-Za-z0-9_-]+", name):
        raise ConfigError(f"chcos new: cell name {name!r}: expected letters, digits, - and _ "
                          "(give --name)")
    if not 1 <= port <= 65535:
        raise ConfigError(f"chcos new: --port {port}: expected a TCP port 1..65535")
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise ConfigError(f"chcos new: {root} exists and is not an empty directory")
    files = {
        "system.toml": SYSTEM, "devices.toml": DEVICES, "tasks/fill.py": TASK,
        "install.chcos": INSTALL, "README.md": README, "tests/test_cell.py": TEST,
        "pytest.ini": "[pytest]\ntestpaths = tests\naddopts = -p no:cacheprovider\n",
        f"chcos-{name}.service": UNIT,
    }
    written = []
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text.format(name=name, host=host, port=port, workdir=root.resolve(),
                                    python=sys.executable), encoding="utf-8")
        written.append(path)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos new DIR``; returns the exit status (2 when the project cannot be written)."""
    ap = argparse.ArgumentParser(
        prog="chcos new",
        description="Create a new cell project in DIR: a system file, a device map (one Modbus "
                    "TCP PLC with a level sensor and a valve), one task, an install script, a "
                    "README and tests that run with plain 'pytest' against a simulated PLC.")
    ap.add_argument("directory", metavar="DIR", help="the new project's directory (empty or "
                                                     "absent)")
    ap.add_argument("--name", help="the system's name (default: the directory's name)")
    ap.add_argument("--host", default="127.0.0.1", help="the PLC's address (default 127.0.0.1)")
    ap.add_argument("--port", type=int, default=5020, help="the PLC's Modbus TCP port "
                                                           "(default 5020)")
    args = ap.parse_args(argv)
    try:
        files = create(args.directory, name=args.name, host=args.host, port=args.port)
    except (ConfigError, OSError) as exc:
        print(f"{exc}", file=sys.stderr)
        return 2
    root = Path(args.directory)
    print(f"cell project in {root}:")
    for f in files:
        print(f"  {f.relative_to(root)}")
    print(f"next: cd {root} && pytest && chcos run system.toml --virtual --duration 5")
    return 0
