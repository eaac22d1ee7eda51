"""driver - the one abstract base every bus driver implements, and the host interface it talks to.

A driver owns one bus (a :class:`chcos.devices.spec.BusSpec`) and the devices on it. All its bus I/O
runs outside the kernel thread (python-can notifier threads, a worker thread for pymodbus, a reader
thread for serial); it reaches the kernel only through the thread-safe :class:`DriverHost` calls.

The interface belongs to the device manager (as Xinu's device switch table belongs to its device
layer): Devtab and the map checks use it without importing any driver, the drivers (``drivers/``,
re-exported by ``drivers.base``) implement it, and :mod:`chcos.devices.registry` finds them by
kind through their entry points.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, Protocol, TypeVar, final

from chcos.devices import options as opts
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.devices.status import DriverStatus
from chcos.errors import DeviceError

_T = TypeVar("_T")
_NO_STATUS = DriverStatus()

#: The write templates of :class:`Driver` no driver overrides, and the hook each calls.
_TEMPLATES = {"write": "_write", "write_now": "_write_now", "write_now_many": "_write_now_many"}
#: Modules whose drivers may still override ``write_now``/``write_now_many`` themselves: none
#: (``drivers.threaded`` implements the hooks): the override of a template is refused everywhere.
_PENDING_RENAME: frozenset[str] = frozenset()


def not_finite(value: Any) -> str | None:
    """Why ``value`` is no finite number (``"expected a finite number, got ..."``), or None if it
    is one (an int, a bool, or a float that is neither NaN nor infinite). The first check of
    every driver's ``check_value``."""
    if isinstance(value, int) or (isinstance(value, float) and math.isfinite(value)):
        return None
    return f"expected a finite number, got {value!r}"


class DriverHost(Protocol):
    """What the device manager offers a driver. Every method is thread-safe unless noted."""

    def deliver(self, device: str, value: Any) -> None:
        """A new reading of sensor ``device`` (decoded by the bus codec, before the device's own
        scale/offset). Lands in the device's last-value buffer as an interrupt."""

    def deliver_now(self, device: str, value: Any) -> None:
        """As :meth:`deliver`, for a reading taken on the kernel thread in a callback of
        :meth:`every` or :meth:`at`: handled at once instead of through the interrupt queue
        (called anywhere else, it is :meth:`deliver`). It overtakes what waits in the
        interrupt queue: a driver that also calls :meth:`fail` uses :meth:`deliver`."""

    def deliver_many(self, readings: Sequence[tuple[str, Any]], at: float | None = None) -> None:
        """Readings ``(device, raw value)`` taken together (one poll's, one frame's signals),
        handed over as one interrupt: one kernel wake-up for all of them, each handled as by
        :meth:`deliver`, in order. ``at``, if given, is when they were received on the kernel
        clock (see :func:`drivers.canbus.receive_time`); staleness and age are judged from it.
        Drivers call it through :func:`deliver_all`."""

    def fail(self, device: str, reason: str) -> None:
        """Device ``device`` failed (heartbeat lost, bus error, timeout); ``reason`` says why."""

    def recover(self, device: str, reason: str = "") -> None:
        """Device ``device`` works again: the event that ended its failure happened (a heartbeat
        back, an error-reset EMCY, a request answered); ``reason`` says which. Never call it for
        a reconnect alone, nor for an unrelated reading."""

    def written(self, device: str, value: Any) -> None:
        """Raw ``value`` (as given to :meth:`Driver.write`) is on the wire for actuator ``device``
        (acknowledged where the protocol acknowledges). Drivers with ``confirms_writes`` report
        every write exactly once, in order: :meth:`written` or :meth:`write_failed`."""

    def write_failed(self, device: str, value: Any, reason: str) -> None:
        """Raw ``value`` for actuator ``device`` did not reach the wire (refused, not answered,
        link down, dropped at stop); ``reason`` says why."""

    def stat(self, bus: str, key: str, n: int = 1, device: str = "", error: bool = False
             ) -> None:
        """Add ``n`` to counter ``key`` of bus ``bus`` (and of ``device`` if given) in the bus
        statistics: ``frames``, ``requests``, ``reconnects``, ``lost`` (frames the OS dropped).
        Error classes go through :meth:`error`; with ``error`` ``n`` errors of class ``key``
        are counted without a report (a driver that reports a streak of the same error once,
        :class:`drivers.reports.Reports`, counts its repeats so). Cheap; callable per frame."""

    def error(self, bus: str, kind: str, detail: str, device: str = "") -> None:
        """Count and report a bus-level error: a malformed frame, an unknown id, garbage on a
        serial line, a timeout, an exception answer. ``kind`` is the error class, a short key
        (``"malformed"``, ``"timeout"``, ``"exception-6"``...) counted in the bus statistics,
        also under ``device`` if the error concerns one device."""

    def every(self, period: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the kernel thread every ``period`` seconds of the kernel clock (virtual or
        real). ``fn`` must not block: it hands work to the driver's own I/O thread. Call only from
        :meth:`Driver.start`."""

    def at(self, when: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` once on the kernel thread at kernel-clock time ``when`` (at once if that
        time has passed). Thread-safe: a driver's I/O thread arms its next poll with it."""

    def now(self) -> float:
        """The kernel clock's current time in seconds."""


def host_clock_virtual(host: DriverHost) -> bool | None:
    """Whether ``host``'s kernel clock is virtual (``host.virtual_clock``, which
    :class:`chcos.devices.devtab.Devtab` has), or None for a host that does not say: a driver
    then passes no receive time (``at``) with its readings."""
    v = getattr(host, "virtual_clock", None)
    return v if isinstance(v, bool) else None


def host_peers_on_clock(host: DriverHost) -> bool:
    """Whether ``host`` says the drivers' peers run on its kernel clock (``host.peers_on_clock``,
    which :class:`chcos.devices.devtab.Devtab` has: simulated slaves stepped on virtual time):
    what a peer does on its own (a heartbeat) is then timed on that clock, not on wall time.
    False for a host that does not say."""
    return getattr(host, "peers_on_clock", False) is True


def deliver_all(host: DriverHost, readings: Sequence[tuple[str, Any]],
                at: float | None = None) -> None:
    """Hand ``readings`` - ``(device, raw value)`` pairs taken together, such as one poll's - to
    ``host`` as one interrupt (:meth:`DriverHost.deliver_many`); nothing for no reading. ``at``,
    if given, is when they were received on the kernel clock (a frame's receive time stamp, see
    :func:`drivers.canbus.receive_time`): staleness and age are then judged from it."""
    if readings:
        host.deliver_many(readings, at)


class Driver(ABC):
    """One bus and its devices.

    Subclasses set :attr:`kind`, and implement :meth:`start` (setting ``self._running`` once
    the bus takes writes), :meth:`_write`, :meth:`stop` (clearing it) and :meth:`settle`.
    :meth:`write` is a template method no driver overrides (a class that tries raises
    ``TypeError`` when it is defined): it refuses a write to anything but an actuator of this
    bus and a write while the driver is not running, counts the rest and only then calls the
    driver's :meth:`_write`. :meth:`check_bus` and :meth:`check_device` validate the
    kind-specific options of a device map without touching any bus (used by ``chcos check``).

    A kind that declares :attr:`Options` and :attr:`Address` (frozen dataclasses of
    :mod:`chcos.devices.options`) gets both checks from them: the map is parsed once, when it is
    checked, and the driver reads the typed values (:meth:`bus_options`, :meth:`address_of`)
    instead of the raw tables.
    """

    kind: ClassVar[str] = ""
    #: True if the driver reports the outcome of every write (``host.written`` /
    #: ``host.write_failed``); otherwise Devtab takes a write as done when it is handed over.
    confirms_writes: ClassVar[bool] = False
    #: True if every actuator of the bus takes numbers only (Devtab refuses anything else).
    numeric_only: ClassVar[bool] = False
    #: The option dataclass of the ``[[bus]]`` table (None: the kind checks by hand in
    #: :meth:`check_bus`).
    Options: ClassVar[type | None] = None
    #: The option dataclass of a device's ``address`` (None: by hand in :meth:`check_device`).
    Address: ClassVar[type | None] = None
    #: Where a device's address takes one of several shapes (a variant chosen by a key or by
    #: the device's direction, see :meth:`address_kind`): every one, for the device-map
    #: reference (each may name itself in a ``VARIANT`` class attribute). Empty: just
    #: :attr:`Address`.
    Addresses: ClassVar[tuple[type, ...]] = ()
    #: False when all this driver does runs on the kernel thread (its I/O in kernel timers and
    #: interrupts, and on virtual time its simulated peer too): nothing is in flight between
    #: two interrupts, so Devtab registers no settler for it and virtual time jumps as soon as
    #: the system is idle (the contract: :mod:`chcos.kernel.scheduler`, "Virtual time"). Read
    #: once, after :meth:`start`; a driver may set it there for the path it took.
    settles: bool = True

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        self.bus = bus
        self.devices = {d.name: d for d in devices}
        self.host = host
        #: True between :meth:`start` and :meth:`stop`: writes are taken (set by the driver).
        self._running = False
        #: Writes handed to :meth:`_write`, per actuator.
        self.write_counts: Counter[str] = Counter()
        #: Writes :meth:`write` refused, per reason (``unknown-device``, ``stopped``).
        self.refused_writes: Counter[str] = Counter()
        #: Frames put on the wire for each actuator, counted by the driver itself (one thread
        #: at a time: its sender) instead of a :meth:`DriverHost.stat` call per frame; the bus
        #: statistics read it as ``frames-sent`` (see :attr:`Devtab.bus_stats`).
        self.sent_frames: Counter[str] = Counter()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        for name, hook in _TEMPLATES.items():
            if name in cls.__dict__ and cls.__module__ not in _PENDING_RENAME:
                raise TypeError(f"{cls.__module__}.{cls.__qualname__} overrides Driver.{name}, "
                                f"the template that checks every write; implement {hook} "
                                f"instead")

    @property
    def running(self) -> bool:
        """True while the driver takes writes (between :meth:`start` and :meth:`stop`)."""
        return self._running

    @classmethod
    def parse_bus(cls, bus: BusSpec) -> tuple[Any, list[str]]:
        """``bus.options`` parsed into :attr:`Options` and the errors found, each as
        ``"<key path>: <what was expected>"``: ``(config, [])`` or ``(None, errors)``; a kind
        without :attr:`Options` gives ``(None, check_bus(bus))``. Called once per bus when a map
        is checked (:mod:`chcos.devices.devmap` keeps the result in :attr:`BusSpec.config`)."""
        if cls.Options is None:
            return None, cls.check_bus(bus)
        return opts.parse(cls.Options, bus.options, bus.key)

    @classmethod
    def address_kind(cls, bus: BusSpec, device: DeviceSpec) -> type | None:
        """The option dataclass ``device``'s address parses into (None: checked by hand in
        :meth:`check_device`). The default: :attr:`Address`; a kind with variants picks one of
        :attr:`Addresses` from the raw address or the device's direction."""
        return cls.Address

    @classmethod
    def address_problems(cls, bus: BusSpec, device: DeviceSpec, addr: Any) -> list[str]:
        """Errors of an address valid by itself (``addr``, parsed) that only the device around
        it shows (its direction, its name), each as ``"<key path>: <what was expected>"``; []
        by default."""
        return []

    @classmethod
    def parse_device(cls, bus: BusSpec, device: DeviceSpec) -> tuple[Any, list[str]]:
        """``device.address`` parsed into :meth:`address_kind`, as :meth:`parse_bus` (kept in
        :attr:`DeviceSpec.addr`), then asked :meth:`address_problems`."""
        kind = cls.address_kind(bus, device)
        if kind is None:
            return None, cls.check_device(bus, device)
        addr, errs = opts.parse(kind, device.address, f"{device.key}.address")
        if addr is not None:
            errs = cls.address_problems(bus, device, addr)
        return (None if errs else addr), errs

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Errors in ``bus.options``, each as ``"<key path>: <what was expected>"``; [] if valid.
        The default: those of :attr:`Options` (none when there is none)."""
        if cls.Options is None:
            return []
        return opts.parse(cls.Options, bus.options, bus.key)[1]

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """Errors in ``device.address`` for this bus kind, like :meth:`check_bus`. The default:
        those :meth:`parse_device` finds (none for an address checked by hand)."""
        if cls.address_kind(bus, device) is None:
            return []
        return cls.parse_device(bus, device)[1]

    @classmethod
    def bus_options(cls, bus: BusSpec, kind: type[_T]) -> _T:
        """The typed options of ``bus`` as ``kind`` (the driver's :attr:`Options`): the value the
        map's check parsed, or, for a spec built in code, ``bus.options`` parsed now. Raises
        :class:`chcos.errors.ConfigError` naming every bad key."""
        if isinstance(bus.config, kind):
            return bus.config
        return opts.parsed(kind, bus.options, bus.key, bus.file)

    @classmethod
    def address_of(cls, device: DeviceSpec, kind: type[_T]) -> _T:
        """The typed address of ``device`` as ``kind`` (the driver's :attr:`Address`), as
        :meth:`bus_options`."""
        if isinstance(device.addr, kind):
            return device.addr
        return opts.parsed(kind, device.address, f"{device.key}.address", device.file)

    @classmethod
    def check_devices(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[
            tuple[DeviceSpec, str]]:
        """Errors between the devices of ``bus`` (each address valid by itself): one device's
        address naming another that is not there. Each as ``(device, "<key path>: <what was
        expected>")``, the path as in :meth:`check_device`; [] if none."""
        return []

    @classmethod
    def check_warnings(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[str]:
        """What is legal in ``bus`` (options and devices, all valid) but bound to misbehave:
        ``chcos check`` prints each as a warning, ``"<key path under the bus>: <why>"`` like
        :meth:`check_bus`; [] if none."""
        return []

    @classmethod
    def encodable(cls, bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
        """The raw values a valid ``device``'s address can carry on the wire, as (lo, hi), or
        None where the driver does not know or the type is unbounded. ``chcos check`` warns when
        an actuator's limits reach outside it (after scale and offset)."""
        return None

    @classmethod
    def poll_period(cls, bus: BusSpec, device: DeviceSpec) -> float | None:
        """Seconds between two readings the driver asks for of a valid sensor ``device``, or None
        if the device sends on its own. ``chcos check`` warns when ``stale_after`` is shorter."""
        return None

    def check_value(self, device: str, value: Any) -> str | None:
        """Why raw ``value`` cannot be written to actuator ``device`` as it is (``"expected ..."``:
        out of the address type's range, not an integer for an integer address...), or None if it
        can. Called by Devtab before :meth:`write`; must not block."""
        return None

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """Raw values :meth:`check_value` accepts for actuator ``device`` without being asked,
        as ``(lo, hi, integral)``: every value in ``lo..hi`` (integers only if ``integral``)
        passes it; outside, Devtab asks :meth:`check_value`, which explains. None (the
        default): ask for every value. Read once per device while the driver runs, so the
        answer must not change; a driver whose check depends on state returns None."""
        return None

    def status(self) -> DriverStatus:
        """What the driver knows of its bus beyond the bus statistics (its remote nodes, its
        SYNC cycle, its controller's error state), for the system map, ``chcos run``'s
        summary, metrics and OPC UA; thread-safe (a scrape thread asks). A driver overrides
        this; the default reads the older :meth:`status_doc` (ValueError if it holds a key
        :class:`DriverStatus` does not know)."""
        doc = self.status_doc()
        return DriverStatus.from_json(doc) if doc else _NO_STATUS

    def status_doc(self) -> dict[str, Any]:
        """The older, untyped form of :meth:`status`, for drivers not moved to it yet: the JSON
        document of a :class:`DriverStatus` (``nodes``, ``sync``, ``bus_state``). The default:
        {} (nothing to show). Read it from :meth:`status` only."""
        return {}

    def flush(self, timeout: float) -> bool:
        """Block until every write queued so far has been put on the wire or reported failed;
        True if done within ``timeout``. Called at shutdown before :meth:`stop`."""
        return self.settle(timeout)

    @abstractmethod
    def start(self) -> None:
        """Open the bus and start the I/O threads; set ``self._running`` once writes can be
        taken. Raises :class:`chcos.errors.BusError`."""

    @final
    def write(self, device: str, value: Any) -> None:
        """Send raw ``value`` to actuator ``device`` without blocking the caller.

        The template of every driver: a ``device`` that is no actuator of this bus is reported
        (``host.error`` kind ``unknown-device``), a write while the driver is not running too
        (``host.error`` kind ``stopped`` and ``host.write_failed``); either is counted in
        :attr:`refused_writes` and, on a driver that does not confirm writes (whose caller has
        no other way to learn of it), raised as :class:`chcos.errors.DeviceError`. Any other
        write is counted in :attr:`write_counts` and handed to :meth:`_write`."""
        spec = self.devices.get(device)
        if spec is None or spec.direction != "actuator":
            actuators = [n for n, d in self.devices.items() if d.direction == "actuator"]
            self._refuse(device, value, "unknown-device",
                         f"write {value!r} to {device!r} on {self.kind} bus {self.bus.name}: "
                         f"not an actuator of this bus; expected one of "
                         f"{', '.join(actuators) or 'none'}")
            return
        if not self._running:
            self._refuse(device, value, "stopped", f"{self.kind} bus {self.bus.name} is not "
                                                   f"running")
            return
        self._handed(device)
        self._write(device, value)

    @final
    def write_now(self, device: str, value: Any) -> bool:
        """Put raw ``value`` for actuator ``device`` on the wire now, in the caller's thread and
        without blocking, confirmed by the answer: True if it is on the wire (counted in
        :attr:`write_counts`, and *not* reported through ``host.written``), False if this
        driver cannot do that right now (nothing done, nothing counted or reported: the caller
        then uses :meth:`write`, which reports what it refuses). Devtab calls it on the kernel
        thread for a value :meth:`check_value` accepted and only when no earlier write of
        ``device`` is outstanding, so order is kept. Never raises for a bus problem.

        The template of the fast path, as :meth:`write` is of the queued one: anything but an
        actuator of this bus, or a driver not running, is False without asking the driver; the
        rest goes to the driver's :meth:`_write_now` and is counted by :meth:`_handed`."""
        return self.write_now_many(((device, value),))[0]

    @final
    def write_now_many(self, writes: Sequence[tuple[str, Any]]) -> list[bool]:
        """:meth:`write_now` for several actuators of this bus at once, in order: which of
        them are on the wire. Devtab's emergency stop puts every safe value out this way before
        it does any bookkeeping. Those :meth:`write_now` would refuse are False; the others go
        to the driver's :meth:`_write_now_many` together."""
        takes = [self._takes(device) for device, _value in writes]
        asked = [w for w, ok in zip(writes, takes, strict=True) if ok]
        sent = iter(self._write_now_many(asked) if asked else ())
        out = [ok and next(sent) for ok in takes]
        for (device, _value), ok in zip(writes, out, strict=True):
            if ok:
                self._handed(device)
        return out

    def _takes(self, device: str) -> bool:
        """True if a write to ``device`` passes :meth:`write`'s checks: an actuator of this bus,
        the driver running."""
        spec = self.devices.get(device)
        return self._running and spec is not None and spec.direction == "actuator"

    def _handed(self, device: str) -> None:
        """The driver's bookkeeping of a write it took (by :meth:`write` or the fast path):
        the one place it is counted."""
        self.write_counts[device] += 1

    def _write_now(self, device: str, value: Any) -> bool:
        """The driver's fast path behind :meth:`write_now`: put raw ``value`` for actuator
        ``device`` (an actuator of this bus, the driver running when it was asked) on the wire
        now, without blocking and without reporting it through ``host.written``; True if it is
        there, False (nothing done) if it cannot now. The default: False (no fast path)."""
        return False

    def _write_now_many(self, writes: Sequence[tuple[str, Any]]) -> list[bool]:
        """The fast path behind :meth:`write_now_many` (each write as :meth:`write_now` checked
        it), in order; a driver that can send several frames under one hold of its link
        overrides it. The default asks :meth:`_write_now` for each."""
        return [self._write_now(device, value) for device, value in writes]

    def _refuse(self, device: str, value: Any, kind: str, reason: str) -> None:
        """Report a write that does not reach :meth:`_write` (see :meth:`write`); also for a
        driver's own :meth:`_write` when it finds the bus stopped under it (``kind`` stopped).
        Raises :class:`DeviceError` on a driver that does not confirm writes."""
        self.refused_writes[kind] += 1
        if kind == "stopped":
            self.host.error(self.bus.name, kind, f"write {value!r} to {device} dropped: {reason}",
                            device)
            self.host.write_failed(device, value, reason)
        else:
            self.host.error(self.bus.name, kind, reason)
        if not self.confirms_writes:
            raise DeviceError(reason)

    @abstractmethod
    def _write(self, device: str, value: Any) -> None:
        """Send raw ``value`` to actuator ``device`` (an actuator of this bus, the driver
        running: :meth:`write` checked both) without blocking the caller (queue it to the I/O
        thread). A driver that confirms writes reports the outcome later through
        :meth:`DriverHost.written` or :meth:`DriverHost.write_failed`."""

    @abstractmethod
    def stop(self) -> None:
        """Clear ``self._running`` (writes are refused from here on), stop the I/O threads and
        close the bus. Idempotent; never raises."""

    @abstractmethod
    def settle(self, timeout: float) -> bool:
        """Block until everything that reached this driver so far has been handed to the host and no
        request is outstanding; True if quiet, False on timeout. The kernel calls it before it jumps
        virtual time ahead, so that virtual-time runs on real protocols are deterministic."""
