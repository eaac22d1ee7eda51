"""direct - the welding cell's devices bound straight onto a :class:`chcos.apps.weld.WeldCell`.

A protocol-free binding for fast runs and tuning: the cell model lives in this process and is
stepped on the kernel clock (``host.every(tick)``), so it runs on virtual time as fast as the CPU
allows and exactly reproducibly. It offers the device table of ``chcos/apps/weld/DEVICES.md`` with
the
same names, units and meaning as the real-bus simulator (``chcos.apps.weld.plant``) and delivers
sensor
readings at the rates the real buses do (the DBC's cycle times, the servo TPDOs, the serial line,
the Modbus polls):

=====================================================  ========  ================================
devices                                                rate      model sensor (for dropouts)
=====================================================  ========  ================================
``theta1``..``theta5`` (rad)                           100 Hz    ``joint1``..``joint5``
``arc_temp`` (degC)                                    50 Hz     ``arc_temperature``
``start_marker``, ``end_marker`` (0/1)                 20 Hz     ``gap_markers``
``intruder`` (0/1)                                     50 Hz     ``intruder``
``linear`` (64 '0'/'1'), ``range`` (mm, -1 = none)     50 Hz     ``linear_sensor``
``arc_volts``, ``arc_amps``, ``wire_speed``,           20 Hz     ``arc_voltage``, ``arc_current``,
``gas_bottle``, ``gas_flow``                                     ``wire_speed``, ...
=====================================================  ========  ================================

A change of ``intruder``, ``start_marker`` or ``end_marker`` is also sent at once (the raw-CAN
nodes send on change as well as periodically). A dropped-out sensor stops delivering (Devtab then
marks it stale after its ``stale_after``); a servo timeout silences its joint and calls
``host.fail(thetaN)``, and ``host.recover`` when it ends.

Actuators: ``target1``..``target5`` (rad), ``drives_enable`` (0/1; 0 holds every joint where it is
and target writes are ignored until it is 1 again), ``volts_set`` (V), ``wire_set`` (mm/s),
``gas_valve`` (0/1). A set-point the model refuses is counted as a bus error
(``host.error``), as a real drive would answer with an error code.

Bus options: ``scenario`` (fault scenario string, :func:`chcos.apps.weld.parse_scenario`, default
none), ``seed`` (int, noise seed, default 0), ``tick`` (model step in s, default 0.01, at most
0.01 so that joints really come at 100 Hz). Device address: ``{ signal = "<name>" }`` where the
name is one of :data:`SENSORS` / :data:`ACTUATORS`; an empty address means the device's own name.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

from chcos.apps.weld import LinearView, Readings, WeldCell, parse_scenario
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError, ChcosError, ConfigError
from drivers.base import Driver, DriverHost

JOINTS = tuple(f"theta{j}" for j in range(1, 6))
TARGETS = tuple(f"target{j}" for j in range(1, 6))


def _linear(r: Readings) -> str:
    return "".join("1" if p else "0" for p in r.linear_pixels)


def _joint(j: int) -> Callable[[Readings], float]:
    def get(r: Readings) -> float:
        return r.joints[j]
    return get


# name -> (period in ticks of 10 ms, model sensor whose dropout silences it, value getter)
SENSORS: dict[str, tuple[int, str, Callable[[Readings], Any]]] = {
    **{f"theta{j + 1}": (1, f"joint{j + 1}", _joint(j)) for j in range(5)},
    "arc_temp": (2, "arc_temperature", lambda r: r.arc_temperature),
    "start_marker": (5, "gap_markers", lambda r: int(r.start_marker)),
    "end_marker": (5, "gap_markers", lambda r: int(r.end_marker)),
    "intruder": (2, "intruder", lambda r: int(r.intruder)),
    "linear": (2, "linear_sensor", _linear),
    "range": (2, "linear_sensor", lambda r: -1.0 if r.range_mm is None else r.range_mm),
    "arc_volts": (5, "arc_voltage", lambda r: r.arc_voltage),
    "arc_amps": (5, "arc_current", lambda r: r.arc_current),
    "wire_speed": (5, "wire_speed", lambda r: r.wire_speed),
    "wire_left": (5, "wire_remaining", lambda r: r.wire_remaining),
    "gas_bottle": (5, "gas_bottle_pressure", lambda r: r.gas_bottle_pressure),
    "gas_flow": (5, "gas_flow", lambda r: r.gas_flow),
}
"""Every sensor this binding offers: its period in 10 ms ticks, the model sensor whose dropout
silences it, and how its value is read from :class:`chcos.apps.weld.Readings`."""

ACTUATORS: tuple[str, ...] = (*TARGETS, "drives_enable", "volts_set", "wire_set", "gas_valve")
"""Every actuator this binding offers."""

ON_CHANGE = ("intruder", "start_marker", "end_marker")
OPTIONS = ("scenario", "seed", "tick")
BASE_TICK = 0.01


class _Cell(WeldCell):
    """The cell model with a linear view computed only when a sample of it is due: the view is
    the model's costliest reading and the sensor is sampled at 50 Hz, half the tick rate."""

    view_due = True
    _view: LinearView | None = None

    def linear_view(self) -> LinearView:
        """The linear sensor's view, recomputed when :attr:`view_due` (else the last one)."""
        if self.view_due or self._view is None:
            self._view = super().linear_view()
        return self._view


class WeldDirectDriver(Driver):
    """Driver for bus kind ``weld-direct``: the cell model in-process (see the module doc).

    :attr:`cell` is the model (for tests and summaries); :attr:`changes` lists
    ``(time, device, value)`` for every change of an on-change device as it was delivered, so the
    reaction latency to an interrupt can be measured; :attr:`writes` counts accepted set-points
    per actuator.
    """

    kind: ClassVar[str] = "weld-direct"

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        errs = self.check_bus(bus)
        if errs:
            raise ConfigError("; ".join(errs))
        try:
            scenario = parse_scenario(str(bus.options.get("scenario", "")))
        except ConfigError as exc:
            raise ConfigError(f"{bus.key}.scenario: {exc}") from exc
        self.tick = float(bus.options.get("tick", BASE_TICK))
        self.cell: WeldCell = _Cell(scenario=scenario, seed=int(bus.options.get("seed", 0)))
        self.signal = {name: str(d.address.get("signal", name)) for name, d in self.devices.items()}
        self.changes: list[tuple[float, str, Any]] = []
        self.writes: dict[str, int] = {}
        self.enabled = True
        self._ticks = 0
        self._failed: set[str] = set()
        self._last: dict[str, Any] = {}

    # ---- checking ---------------------------------------------------------------------------
    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Errors in the bus options ``scenario``, ``seed``, ``tick``."""
        errs = [f"{bus.key}.{k}: unknown option for a weld-direct bus; valid options: "
                f"{', '.join(OPTIONS)}" for k in bus.options if k not in OPTIONS]
        scen = bus.options.get("scenario", "")
        if not isinstance(scen, str):
            errs.append(f"{bus.key}.scenario: expected a scenario string, got {scen!r}")
        else:
            try:
                parse_scenario(scen)
            except ConfigError as exc:
                errs.append(f"{bus.key}.scenario: {exc}")
        seed = bus.options.get("seed", 0)
        if not isinstance(seed, int) or isinstance(seed, bool):
            errs.append(f"{bus.key}.seed: expected an integer, got {seed!r}")
        tick = bus.options.get("tick", BASE_TICK)
        if (not isinstance(tick, int | float) or isinstance(tick, bool)
                or not (math.isfinite(tick) and 0 < tick <= BASE_TICK)):
            errs.append(f"{bus.key}.tick: expected seconds, 0 < tick <= {BASE_TICK}, got {tick!r}")
        return errs

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """The address may only hold ``signal``, naming a sensor or actuator of the cell that
        matches the device's direction."""
        key = f"{device.key}.address"
        errs = [f"{key}.{k}: unknown key; valid keys: signal" for k in device.address
                if k != "signal"]
        name = device.address.get("signal", device.name)
        known = SENSORS if device.direction == "sensor" else ACTUATORS
        if name not in known:
            errs.append(f"{key}.signal: {name!r} is not a {device.direction} of the welding cell; "
                        f"expected one of {', '.join(known)}")
        return errs

    # ---- running ----------------------------------------------------------------------------
    def start(self) -> None:
        """Register the model step on the kernel clock. Raises BusError if the device list does
        not fit the cell."""
        bad = [n for n, d in self.devices.items() if self.check_device(self.bus, d)]
        if bad:
            raise BusError(f"bus {self.bus.name}: devices {', '.join(bad)} are not devices of the "
                           "welding cell")
        self._running = True
        self.host.every(self.tick, self._step)

    def stop(self) -> None:
        """Stop stepping the model (the host's periodic calls become no-ops)."""
        self._running = False

    def settle(self, timeout: float) -> bool:
        """Always quiet: everything is delivered synchronously on the kernel thread."""
        return True

    def _step(self) -> None:
        if not self._running:
            return
        cell = self.cell
        if not self.enabled:
            cell.targets = list(cell.joints)  # safe torque off: hold every joint where it is
        cell.step(self.tick)
        self._ticks += 1
        n = round(self._ticks * self.tick / BASE_TICK)
        prev = round((self._ticks - 1) * self.tick / BASE_TICK)
        if isinstance(cell, _Cell):
            cell.view_due = n // 2 != prev // 2
            r = cell.readings()
            cell.view_due = True
        else:
            r = cell.readings()
        now = self.host.now()
        for j, ok in enumerate(r.servo_ok):
            name = JOINTS[j]
            if name not in self.signal:
                continue
            if not ok and name not in self._failed:
                self._failed.add(name)
                self.host.fail(name, f"servo drive of joint {j + 1} timed out (no position)")
            elif ok and name in self._failed:
                self._failed.discard(name)
                self.host.recover(name)
        for dev, sig in self.signal.items():
            spec = SENSORS.get(sig)
            if spec is None:
                continue
            period, model_name, get = spec
            if model_name in r.silent:
                continue
            value = get(r)
            due = n // period != prev // period
            changed = sig in ON_CHANGE and dev in self._last and self._last[dev] != value
            if changed:
                self.changes.append((now, dev, value))
            if due or changed:
                self._last[dev] = value
                self.host.deliver(dev, value)

    def _write(self, device: str, value: Any) -> None:
        """Apply a set-point to the model at once. A value the model refuses is reported with
        ``host.error`` (kind ``refused``)."""
        sig = self.signal[device]
        cell = self.cell
        try:
            if sig in TARGETS:
                if self.enabled:
                    cell.set_joint_target(TARGETS.index(sig) + 1, float(value))
            elif sig == "drives_enable":
                on = bool(round(float(value)))
                if on and not self.enabled:
                    cell.targets = list(cell.joints)
                self.enabled = on
            elif sig == "volts_set":
                cell.set_voltage(float(value))
            elif sig == "wire_set":
                cell.set_wire_speed(float(value))
            else:
                cell.set_gas_valve(bool(round(float(value))))
        except (ChcosError, ValueError, TypeError) as exc:
            self.host.error(self.bus.name, "refused", f"{device} <- {value!r}: {exc}")
            return
        self.writes[device] = self.writes.get(device, 0) + 1
