"""signal - a sensor generator for demos and load tests, driven by the kernel clock.

Every sensor on a ``signal`` bus produces a waveform sampled at ``rate_hz`` through
``host.every()``, so it runs on virtual time as well as real time. Actuators behave as on a
``memory`` bus (writes kept in :attr:`SignalDriver.store`).

Bus options: ``history`` (as for ``memory``). Sensor address keys:

- ``waveform``: ``"sine" | "square" | "ramp" | "constant" | "random"`` (required)
- ``rate_hz``: samples per second, > 0 (required)
- ``amplitude`` (default 1.0), ``center`` (default 0.0): the value swings over
  ``center ± amplitude`` (``ramp`` rises from ``center - amplitude`` to ``center + amplitude``)
- ``period`` (seconds, > 0, default 1.0) and ``phase`` (seconds, default 0.0) for sine/square/ramp
- ``value`` (default ``center``): the value of ``constant``
- ``seed`` (int, default 0): the seed of ``random`` (uniform over ``center ± amplitude``)

Values are computed from ``host.now()``, so a run is reproducible on virtual time.

``waveform = "echo"`` is a plant that answers its actuator at once, as a position feedback
follows its command in a simulated cell (or an echo peer turns a frame around on a bus):
``actuator`` (required) names an actuator of the same bus on the same machine; every value
written to it is delivered as a reading of this sensor straight away, through the interrupt
queue like any reading; every ``1 / rate_hz`` the sensor also reads the value last written
(``value``, default 0.0, before the first write), so a task that answers each reading with a
write runs flat out from the first sample, with no reading left unserved. Other waveform keys
do not apply to it.

Actuator addresses must be empty.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Mapping, Sequence
from typing import Any, TypeGuard

from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.base import DriverHost
from drivers.memory import MemoryDriver

WAVEFORMS = ("sine", "square", "ramp", "constant", "random", "echo")
ADDRESS_KEYS = ("waveform", "rate_hz", "amplitude", "center", "period", "phase", "value", "seed",
                "actuator")
#: the keys an echo sensor takes (the others shape a waveform it does not have)
ECHO_KEYS = ("waveform", "rate_hz", "value", "actuator")


def _num(v: object) -> TypeGuard[int | float]:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def make_waveform(address: Mapping[str, Any]) -> Callable[[float], float]:
    """The function time -> value described by a (checked) signal-device address (not an
    echo: see :class:`SignalDriver`). Raises ValueError for an echo address."""
    kind = address["waveform"]
    if kind == "echo":
        raise ValueError("an echo sensor reads its actuator back; it has no waveform of time")
    amp = float(address.get("amplitude", 1.0))
    center = float(address.get("center", 0.0))
    period = float(address.get("period", 1.0))
    phase = float(address.get("phase", 0.0))
    if kind == "sine":
        return lambda t: center + amp * math.sin(2 * math.pi * (t + phase) / period)
    if kind == "square":
        return lambda t: center + (amp if ((t + phase) % period) < period / 2 else -amp)
    if kind == "ramp":
        return lambda t: center - amp + 2 * amp * (((t + phase) % period) / period)
    if kind == "constant":
        value = float(address.get("value", center))
        return lambda t: value
    rng = random.Random(int(address.get("seed", 0)))
    return lambda t: rng.uniform(center - amp, center + amp)


def _holding(held: list[Any]) -> Callable[[float], Any]:
    """An echo sensor's sample: the value ``held[0]`` (its actuator's last write)."""
    def value(t: float) -> Any:
        return held[0]
    return value


class SignalDriver(MemoryDriver):
    """Driver for kind ``signal``: waveform sensors on the kernel clock; actuators (and the
    ``history`` option) as on a ``memory`` bus."""

    kind = "signal"
    Address = None      # waveform addresses are checked by hand (check_device)

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self.samples = 0
        #: each echoed actuator: its echo sensors
        self._echoes: dict[str, list[str]] = {}
        #: each echo sensor's held value (the last one written to its actuator), in a list
        #: that its sampler reads
        self._held: dict[str, list[Any]] = {}
        for d in devices:
            if d.direction == "sensor" and d.address.get("waveform") == "echo":
                self._echoes.setdefault(d.address["actuator"], []).append(d.name)
                self._held[d.name] = [float(d.address.get("value", 0.0))]

    @classmethod
    def poll_period(cls, bus: BusSpec, device: DeviceSpec) -> float | None:
        """One sample period, ``1 / rate_hz``."""
        return 1.0 / float(device.address["rate_hz"])

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """Checks a sensor's waveform address; an actuator takes no address."""
        key = f"{device.key}.address"
        a = device.address
        if device.direction == "actuator":
            return [f"{key}.{k}: unknown key; an actuator on a signal bus takes no address"
                    for k in a]
        errs = [f"{key}.{k}: unknown key; valid keys: {', '.join(ADDRESS_KEYS)}"
                for k in a if k not in ADDRESS_KEYS]
        echo = a.get("waveform") == "echo"
        if echo:
            errs += [f"{key}.{k}: not for an echo sensor; it takes {', '.join(ECHO_KEYS)}"
                     for k in a if k in ADDRESS_KEYS and k not in ECHO_KEYS]
            act = a.get("actuator")
            if not isinstance(act, str) or not act:
                errs.append(f"{key}.actuator: expected the name of an actuator of bus "
                            f"{bus.name!r} on machine {device.machine}, got {act!r}")
        elif "actuator" in a:
            errs.append(f"{key}.actuator: only for waveform \"echo\", not "
                        f"{a.get('waveform')!r}")
        if a.get("waveform") not in WAVEFORMS:
            errs.append(f"{key}.waveform: expected one of {', '.join(WAVEFORMS)}, "
                        f"got {a.get('waveform')!r}")
        rate = a.get("rate_hz")
        if not _num(rate) or rate <= 0:
            errs.append(f"{key}.rate_hz: expected samples per second > 0, got {rate!r}")
        for k in ("amplitude", "center", "phase", "value"):
            if k in a and not _num(a[k]):
                errs.append(f"{key}.{k}: expected a finite number, got {a[k]!r}")
        if "period" in a and (not _num(a["period"]) or a["period"] <= 0):
            errs.append(f"{key}.period: expected seconds > 0, got {a['period']!r}")
        seed = a.get("seed", 0)
        if not isinstance(seed, int) or isinstance(seed, bool):
            errs.append(f"{key}.seed: expected an integer, got {seed!r}")
        return errs

    @classmethod
    def check_devices(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[
            tuple[DeviceSpec, str]]:
        """An echo sensor's ``actuator`` must be an actuator of this bus on its machine."""
        actuators = {(d.name, d.machine) for d in devices if d.direction == "actuator"}
        errs = []
        for d in devices:
            act = d.address.get("actuator")
            if (d.direction == "sensor" and d.address.get("waveform") == "echo"
                    and (act, d.machine) not in actuators):
                have = sorted(n for n, m in actuators if m == d.machine)
                errs.append((d, f"actuator: expected an actuator of bus {bus.name!r} on machine "
                                f"{d.machine} ({', '.join(have) or 'it has none'}), got {act!r}"))
        return errs

    def start(self) -> None:
        """Register one ``host.every`` sampler per sensor."""
        self._running = True
        for d in self.devices.values():
            if d.direction != "sensor":
                continue
            held = self._held.get(d.name)
            wave = make_waveform(d.address) if held is None else _holding(held)
            self.host.every(1.0 / float(d.address["rate_hz"]), self._sampler(d.name, wave))

    def _sampler(self, name: str, wave: Callable[[float], Any]) -> Callable[[], None]:
        def sample() -> None:
            if self._running:
                self.samples += 1
                self.host.deliver_now(name, wave(self.host.now()))  # (a kernel timer's)
        return sample

    def _write(self, device: str, value: Any) -> None:
        """Keep the write; each echo sensor of ``device`` reads it at once (an interrupt, in
        order with the driver's other reports) and holds it for its sampler."""
        self.store.put(device, value)
        echoes = self._echoes.get(device)
        if echoes is not None:
            deliver = self.host.deliver
            for name in echoes:
                self._held[name][0] = value
                deliver(name, value)

    def stop(self) -> None:
        """Stop sampling (the host's periodic calls become no-ops)."""
        self._running = False
