"""bench_modbus_virtual - the real-time factor of a Modbus-only cell in virtual time (issue 47):
the same device map, its slaves simulated in this process, run side by side in one run

* ``direct`` - the driver's requests and the slaves on the kernel's thread (the bus's
  ``direct``: the request's bytes handed to the slave in a call, every timeout a kernel timer;
  what ``chcos run --virtual`` and the pytest plugin do);
* ``sockets`` - the same slaves behind loopback sockets (a Modbus TCP server, RTU frames over
  TCP), the drivers' worker threads, and the kernel's settle rounds waiting for them (how a
  virtual cell ran before).

The cell: a Modbus TCP device with 24 sensors (holding and input registers, 16/32-bit, in three
runs) and 2 actuators, and an RTU line with two units of 3 sensors and an actuator each, polled
every 0.1 s; a task writes the actuators every 0.1 s; the sensors follow sine scripts (or, with
``--no-scripts``, stay put: what the buses alone cost). Prints,
for each, the virtual seconds per wall second (the real-time factor), the CPU seconds per
virtual second and the readings per virtual second, best of ``--repeat`` interleaved runs.

``python -m tools.bench_modbus_virtual [--seconds V] [--repeat N]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

from chcos.apps.sim.from_map import simulate
from chcos.devices.devmap import load
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System

M = "tools.bench_modbus_virtual"


def cell_map() -> str:
    """The device map (see the module doc)."""
    out = ['[[bus]]\nname = "plc"\nkind = "modbus-tcp"\nhost = "127.0.0.1"\nport = 15020\n'
           'timeout = 0.5\n',
           '[[bus]]\nname = "line"\nkind = "modbus-rtu"\nport = "/dev/ttyUSB0"\n'
           'baudrate = 115200\ntimeout = 0.3\n']
    for i in range(24):
        table = "holding" if i < 16 else "input"
        typ = "int32" if i % 3 == 0 else "uint16"
        address = 100 * (i % 3) + 2 * i
        out.append(f'[[device]]\nname = "s{i}"\ndirection = "sensor"\nbus = "plc"\n'
                   f'address = {{ table = "{table}", address = {address}, type = "{typ}" }}\n')
    for i in range(2):
        out.append(f'[[device]]\nname = "a{i}"\ndirection = "actuator"\nbus = "plc"\n'
                   f'address = {{ table = "holding", address = {500 + i} }}\nsafe_value = 0\n')
    for unit in (1, 2):
        for i in range(3):
            out.append(f'[[device]]\nname = "u{unit}s{i}"\ndirection = "sensor"\nbus = "line"'
                       f'\naddress = {{ unit = {unit}, table = "input", address = {i} }}\n')
        out.append(f'[[device]]\nname = "u{unit}a"\ndirection = "actuator"\nbus = "line"\n'
                   f'address = {{ unit = {unit}, table = "holding", address = 9 }}\n'
                   f'safe_value = 0\n')
    return "\n".join(out)


ACTUATORS = ("a0", "a1", "u1a", "u2a")


async def writer(ctx: Any, cmd: Any) -> None:
    """Writes every actuator every 0.1 s, values 0..99."""
    n = 0
    while True:
        for name in ACTUATORS:
            ctx.write(name, n % 100)
        n += 1
        await ctx.sleep(0.1)


def run(mode: str, seconds: float, tmp: Path, scripts: bool = True
        ) -> tuple[float, float, float]:
    """One run of ``seconds`` virtual seconds: (real-time factor, CPU s per virtual s,
    readings per virtual s)."""
    path = tmp / "cell.toml"
    path.write_text(cell_map(), encoding="utf-8")
    slaves = simulate(load([path]), direct=mode == "direct")
    if scripts:
        slaves.values([f"s{i}=sine({100 + i}, 10, {1 + i / 10})" for i in range(24)]
                      + [f"u{u}s{i}=sine(50, 5, 2)" for u in (1, 2) for i in range(3)])
    system = System(slaves.devmap, clock=VirtualClock(), base_dir=tmp)
    slaves.attach(system.kernel)
    system.devtab.peers_on_clock = True
    try:
        system.execute("install -m0 sysfile")
        system.execute(f"install -m0o{len(ACTUATORS)} --code={M}:writer W "
                       f"{' '.join(ACTUATORS)}")
        system.run_for(1.0)                  # connected, every unit answered
        system.invoke("W", {})
        before = sum(e.readings for e in system.devtab)
        wall, cpu = time.perf_counter(), time.process_time()
        system.run_for(seconds)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        readings = sum(e.readings for e in system.devtab) - before
    finally:
        system.shutdown()
        slaves.close()
    return seconds / wall, cpu / seconds, readings / seconds


def main() -> None:
    """Both modes, interleaved; prints the best of each."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="virtual seconds per run")
    ap.add_argument("--repeat", type=int, default=3, help="interleaved runs of each mode")
    ap.add_argument("--no-scripts", action="store_true",
                    help="constant sensors: what the buses alone cost (the scripts are applied "
                         "every 10 ms of virtual time, whatever the poll period)")
    args = ap.parse_args()
    best: dict[str, tuple[float, float, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.repeat):
            for mode in ("sockets", "direct"):
                got = run(mode, args.seconds, Path(tmp), not args.no_scripts)
                if mode not in best or got[0] > best[mode][0]:
                    best[mode] = got
    print(f"Modbus-only cell (30 sensors{'' if args.no_scripts else ' on sine scripts'}, 4 "
          f"actuators written every 0.1 s, TCP device and a 2-unit RTU line polled every "
          f"0.1 s), {args.seconds:g} virtual s, best of {args.repeat}")
    print("  mode       real-time factor   CPU-s per virtual s   readings per virtual s")
    for mode in ("sockets", "direct"):
        f, c, r = best[mode]
        print(f"  {mode:<9} {f:12.1f}x {c:18.4f} {r:20.0f}")
    print(f"  direct / sockets: {best['direct'][0] / best['sockets'][0]:.1f}x the factor")


if __name__ == "__main__":
    main()
