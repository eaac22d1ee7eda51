"""signal - a sensor generator for demos and load tests, driven by the kernel clock.

Every sensor on a ``signal`` bus produces a waveform sampled at ``rate_hz`` through
``host.every()``, so it runs on virtual time as well as real time; values are computed from
``host.now()``, so a run is reproducible on virtual time. Actuators behave as on a ``memory``
bus (writes kept in :attr:`SignalDriver.store`; the bus options are memory's, ``history``) and
take no address.

A sensor's address is one of two variants, chosen by ``waveform``: a waveform of time
(:class:`WaveAddress`: ``sine``, ``square``, ``ramp``, ``constant``, ``random``) swinging over
``center ± amplitude``, or an ``echo`` (:class:`EchoAddress`): a plant that answers its actuator
at once, as a position feedback follows its command in a simulated cell (or an echo peer turns a
frame around on a bus). ``actuator`` names an actuator of the same bus on the same machine; every
value written to it is delivered as a reading of this sensor straight away, through the
interrupt queue like any reading; every ``1 / rate_hz`` the sensor also reads the value last
written (``value`` before the first write), so a task that answers each reading with a write
runs flat out from the first sample, with no reading left unserved. Each key, its default and
its meaning are the fields below (the device-map reference is generated from them).
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

from chcos.devices.options import nonempty, option, positive
from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.base import DriverHost
from drivers.memory import MemoryDriver

Waveform = Literal["sine", "square", "ramp", "constant", "random", "echo"]
WAVEFORMS: tuple[str, ...] = Waveform.__args__   # type: ignore[attr-defined]


_WAVEFORM = ("the shape (`ramp` rises from `center - amplitude` to `center + amplitude` each "
             "period, `random` is uniform over `center ± amplitude`, `echo` reads `actuator` "
             "back: each write at once, as an interrupt, and every sample the last one)")


def _finite(v: Any) -> str | None:
    return None if math.isfinite(v) else "a finite number"


@dataclass(frozen=True)
class WaveAddress:
    """A sensor's waveform of time."""

    VARIANT: ClassVar[str] = "waveform"
    waveform: Waveform = option(doc=_WAVEFORM)
    rate_hz: float = option(unit="Hz", doc="samples per second", check=positive)
    amplitude: float = option(1.0, doc="peak deviation from center", check=_finite)
    center: float = option(0.0, doc="mid value", check=_finite)
    period: float = option(1.0, unit="s", doc="waveform period", check=positive)
    phase: float = option(0.0, unit="s", doc="time added to the clock's before the waveform "
                          "is taken", check=_finite)
    value: float | None = option(None, default_doc="center", doc="the `constant` value",
                                 check=_finite)
    seed: int = option(0, doc="the `random` generator's seed")


@dataclass(frozen=True)
class EchoAddress:
    """A sensor that reads its actuator back."""

    VARIANT: ClassVar[str] = "echo"
    waveform: Waveform = option(doc=_WAVEFORM)
    rate_hz: float = option(unit="Hz", doc="samples per second", check=positive)
    actuator: str = option(doc="the actuator this sensor reads back (same bus, same machine)",
                           check=nonempty)
    value: float = option(0.0, doc="the reading before the first write", check=_finite)


@dataclass(frozen=True)
class ActuatorAddress:
    """An actuator's address on a signal bus: no key."""

    NO_KEYS: ClassVar[str] = "an actuator on a signal bus takes no address"


def make_waveform(address: WaveAddress) -> Callable[[float], float]:
    """The function time -> value described by a waveform address; ValueError for an
    ``echo`` (it reads its actuator back, see :class:`SignalDriver`)."""
    kind = address.waveform
    if kind == "echo":
        raise ValueError("an echo sensor reads its actuator back; it has no waveform of time")
    amp, center, period, phase = address.amplitude, address.center, address.period, address.phase
    if kind == "sine":
        return lambda t: center + amp * math.sin(2 * math.pi * (t + phase) / period)
    if kind == "square":
        return lambda t: center + (amp if ((t + phase) % period) < period / 2 else -amp)
    if kind == "ramp":
        return lambda t: center - amp + 2 * amp * (((t + phase) % period) / period)
    if kind == "constant":
        value = center if address.value is None else address.value
        return lambda t: value
    rng = random.Random(address.seed)
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
    Address = None      # a variant per device: address_kind
    Addresses = (WaveAddress, EchoAddress, ActuatorAddress)

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self.samples = 0
        #: each sensor's address, parsed
        self._addr: dict[str, WaveAddress | EchoAddress] = {}
        #: each echoed actuator: its echo sensors
        self._echoes: dict[str, list[str]] = {}
        #: each echo sensor's held value (the last one written to its actuator), in a list
        #: that its sampler reads
        self._held: dict[str, list[Any]] = {}
        for d in devices:
            if d.direction != "sensor":
                continue
            addr = self._sensor_address(bus, d)
            self._addr[d.name] = addr
            if isinstance(addr, EchoAddress):
                self._echoes.setdefault(addr.actuator, []).append(d.name)
                self._held[d.name] = [addr.value]

    @classmethod
    def address_kind(cls, bus: BusSpec, device: DeviceSpec) -> type:
        """An actuator's (no key), an echo sensor's or a waveform sensor's address."""
        if device.direction == "actuator":
            return ActuatorAddress
        return EchoAddress if device.address.get("waveform") == "echo" else WaveAddress

    @classmethod
    def _sensor_address(cls, bus: BusSpec, device: DeviceSpec) -> WaveAddress | EchoAddress:
        """A (valid) sensor's address, parsed."""
        kind: type[WaveAddress | EchoAddress] = (
            EchoAddress if cls.address_kind(bus, device) is EchoAddress else WaveAddress)
        return cls.address_of(device, kind)

    @classmethod
    def poll_period(cls, bus: BusSpec, device: DeviceSpec) -> float | None:
        """One sample period, ``1 / rate_hz``."""
        return 1.0 / cls._sensor_address(bus, device).rate_hz

    @classmethod
    def check_devices(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[
            tuple[DeviceSpec, str]]:
        """An echo sensor's ``actuator`` must be an actuator of this bus on its machine."""
        actuators = {(d.name, d.machine) for d in devices if d.direction == "actuator"}
        errs = []
        for d in devices:
            if d.direction != "sensor" or cls.address_kind(bus, d) is not EchoAddress:
                continue
            act = cls.address_of(d, EchoAddress).actuator
            if (act, d.machine) not in actuators:
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
            addr = self._addr[d.name]
            wave = (make_waveform(addr) if isinstance(addr, WaveAddress)
                    else _holding(self._held[d.name]))
            self.host.every(1.0 / addr.rate_hz, self._sampler(d.name, wave))

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
