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

WAVEFORMS = ("sine", "square", "ramp", "constant", "random")
ADDRESS_KEYS = ("waveform", "rate_hz", "amplitude", "center", "period", "phase", "value", "seed")


def _num(v: object) -> TypeGuard[int | float]:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def make_waveform(address: Mapping[str, Any]) -> Callable[[float], float]:
    """The function time -> value described by a (checked) signal-device address."""
    kind = address["waveform"]
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


class SignalDriver(MemoryDriver):
    """Driver for kind ``signal``: waveform sensors on the kernel clock; actuators (and the
    ``history`` option) as on a ``memory`` bus."""

    kind = "signal"

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self.samples = 0

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

    def start(self) -> None:
        """Register one ``host.every`` sampler per sensor."""
        self._running = True
        for d in self.devices.values():
            if d.direction == "sensor":
                self.host.every(1.0 / float(d.address["rate_hz"]),
                                self._sampler(d.name, make_waveform(d.address)))

    def _sampler(self, name: str, wave: Callable[[float], float]) -> Callable[[], None]:
        def sample() -> None:
            if self._running:
                self.samples += 1
                self.host.deliver_now(name, wave(self.host.now()))  # (a kernel timer's)
        return sample

    def stop(self) -> None:
        """Stop sampling (the host's periodic calls become no-ops)."""
        self._running = False
