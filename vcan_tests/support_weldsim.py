"""support_weldsim - a System on a VirtualClock attached to a WeldSim over real protocols.

:func:`make_rig` binds a copy of ``chcos/apps/weld/maps/weld_cell.toml`` to fresh virtual CAN
channels and
free loopback ports, builds the simulator (first: the drivers connect to it), boots machine 0,
installs four trivial tasks (:func:`act`) whose inputs and outputs are every device of the cell
(the axes' sensors aside), and attaches the simulator to the kernel. Tasks are commanded with
:meth:`WeldRig.command`; :meth:`WeldRig.enable_drives` enables the five CiA 402 joint drives.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.apps.weld.faults import Scenario
from chcos.apps.weld.model import CellConfig
from chcos.apps.weld.plant import WeldSim
from chcos.apps.weld.simmap import cell_devmap
from chcos.devices.entry import DeviceEntry
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from vcan_tests.netutil import free_port, unique_channel

M = "vcan_tests.support_weldsim"

#: task -> (inputs, outputs): together every device of weld_cell.toml.
TASKS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "JOINTS": (("theta1", "theta2", "theta3", "theta4", "theta5"),
               ("target1", "target2", "target3", "target4", "target5")),
    "POWER": (("arc_temp", "arc_volts", "arc_amps", "wire_speed", "wire_left", "gas_bottle",
               "gas_flow"),
              ("drives_enable", "volts_set", "wire_set", "gas_valve")),
    "SEAM": (("linear", "range", "start_marker", "end_marker", "intruder"), ()),
    "DRIVES": ((), ("joint1", "joint2", "joint3", "joint4", "joint5")),
}
SENSORS: tuple[str, ...] = tuple(s for ins, _ in TASKS.values() for s in ins)

QUIET = CellConfig(noise_joint=0.0, noise_temp=0.0, noise_voltage=0.0, noise_current=0.0,
                   noise_pressure=0.0, noise_flow=0.0, noise_wire=0.0)
"""A cell without measurement noise: readings equal the state, to compare exactly."""


async def act(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Read each input named in ``cmd["read"]`` into ``cmd["seen"]``, then write each actuator
    value of ``cmd["write"]`` in order."""
    for name in cmd.get("read", ()):
        cmd.setdefault("seen", {})[name] = await ctx.read(name)
    for name, value in cmd.get("write", {}).items():
        ctx.write(name, value)


@dataclass
class WeldRig:
    """The simulator, the System and the device-map copy they share."""

    sim: WeldSim
    system: System
    mapfile: Path

    def command(self, task: str, **writes: float) -> dict[str, Any]:
        """Invoke ``task`` to write ``writes`` (actuator -> value); returns the command."""
        cmd: dict[str, Any] = {"write": writes}
        self.system.invoke(task, cmd)
        return cmd

    def read(self, task: str, names: Sequence[str]) -> dict[str, Any]:
        """Invoke ``task`` to read ``names`` through its input ports; the values land in the
        returned command's ``"seen"`` once the kernel has run."""
        cmd: dict[str, Any] = {"read": list(names)}
        self.system.invoke(task, cmd)
        return cmd

    def enable_drives(self, limit: float = 1.0) -> None:
        """Enable the five joint drives through their axes (the command code ENABLE written to
        each) and run until every drive, on its side, is OPERATION ENABLED and the master has
        the write confirmed; AssertionError naming their states if not within ``limit`` s of
        virtual time."""
        from drivers.canopen_axis import AxisCode

        self.command("DRIVES", **{f"joint{n}": float(AxisCode.ENABLE) for n in range(1, 6)})
        waited = 0.0
        drives = self.sim.servo.drives if self.sim.servo is not None else {}
        while not (all(d.enabled for d in drives.values())
                   and all(self.value(f"joint{n}") == AxisCode.ENABLE for n in range(1, 6))):
            assert waited < limit, {n: d.power.name for n, d in drives.items()}
            self.run(0.02)
            waited += 0.02

    def run(self, seconds: float) -> None:
        """Run the system (and the simulator with it) for ``seconds`` of virtual time."""
        self.system.run_for(seconds)

    def entry(self, device: str) -> DeviceEntry:
        """Devtab's entry of ``device``."""
        return self.system.devtab.get(device)

    def value(self, device: str) -> Any:
        """Devtab's last value of ``device``."""
        return self.entry(device).value

    def status(self, device: str) -> str:
        """Devtab's status of ``device`` (``OK``, ``stale``, ``failed``...)."""
        return self.entry(device).status.value

    def close(self) -> None:
        """Shut the System down (safe values out, the simulator going on on wall-clock time
        meanwhile), then the simulator."""
        try:
            self.sim.continue_realtime()
            self.system.shutdown()
        finally:
            self.sim.close()


def make_rig(tmp_path: Path, *, scenario: Scenario | str | None = None, seed: int = 0,
             config: CellConfig | None = None, attach_first: bool = False) -> WeldRig:
    """A booted System on virtual time talking to a fresh WeldSim (see the module doc);
    ``attach_first`` attaches the simulator before machine 0 is booted."""
    channels = unique_channel("weld-co"), unique_channel("weld-can")
    ports = free_port(), free_port()
    mapfile = cell_devmap(tmp_path, canopen_channel=channels[0], sensor_channel=channels[1],
                          modbus_port=ports[0], serial_port=ports[1])
    sim = WeldSim(canopen_channel=channels[0], sensor_channel=channels[1], modbus_port=ports[0],
                  serial_port=ports[1], scenario=scenario, seed=seed, config=config)
    try:
        system = System([mapfile], clock=VirtualClock(), base_dir=tmp_path)
    except BaseException:
        sim.close()
        raise
    rig = WeldRig(sim, system, mapfile)
    try:
        if attach_first:
            sim.attach(system.kernel)
        system.execute("install -m0 sysfile")
        for task, (ins, outs) in TASKS.items():
            system.execute(f"install -m0i{len(ins)}o{len(outs)} --code={M}:act {task} "
                           f"{' '.join(ins + outs)}")
        if not attach_first:
            sim.attach(system.kernel)
    except BaseException:
        rig.close()
        raise
    return rig
