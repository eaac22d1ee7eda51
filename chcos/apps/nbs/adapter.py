"""adapter - run an NBS executor on a chcos System: same kernel clock, same Devtab, same load.

The NBS baseline (:mod:`chcos.apps.nbs.executor`) needs a
:class:`~chcos.apps.nbs.scheduling.Scheduler` and a
:class:`~chcos.apps.nbs.executor.DeviceIO`. Here both come from a chcos
:class:`~chcos.system.embedded.System`,
so NBS and CHC are compared on identical devices, drivers and load:

* :class:`KernelScheduler` - ``now()`` is the kernel clock (virtual or real), ``every()`` a
  drift-free periodic kernel timer; the executor's cycle runs on the kernel thread between task
  steps, exactly where a chcos interrupt handler or timer runs. ``run_until()`` drives the kernel
  on the calling thread (for virtual-time runs).
* :class:`DevtabIO` - ``read`` is a sensor's last value in its Devtab last-value buffer (None
  before the first reading), ``write`` goes through :meth:`~chcos.devices.devtab.Devtab.write`
  (limits,
  scaling, the driver, the ``on_write`` hooks), ``arrived`` is the Devtab time stamp of the
  current reading (kernel clock), so the executor sees a new value even when it equals the old.

:func:`attach` builds a ready :class:`NbsOnSystem` (executor + scheduler + io).
Errors: :class:`~chcos.errors.KernelError` for misuse of the scheduler (bad period, kernel already
running on another thread, a failing NBS cycle); :class:`~chcos.errors.DeviceError` for an unknown
device, a read of an actuator or a write the Devtab refuses.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from chcos.apps.nbs.executor import DEFAULT_PERIOD, DeviceIO, Level, NbsExecutor
from chcos.devices.devtab import Devtab
from chcos.errors import DeviceError, KernelError
from chcos.kernel.scheduler import Kernel, Timer

__all__ = ["DevtabIO", "KernelScheduler", "NbsOnSystem", "attach"]

_EPSILON = 1e-9  # the executor's own tolerance for "due at" (float rounding of k * period)


class KernelScheduler:
    """The NBS :class:`~chcos.apps.nbs.scheduling.RunnableScheduler` on a chcos kernel.

    Callbacks armed with :meth:`every` run as kernel timers. An exception in one stops the
    kernel and is raised again by :meth:`run_until` as KernelError (the kernel itself would only
    log a failing timer and go on, hiding a broken baseline).
    """

    def __init__(self, kernel: Kernel) -> None:
        self.kernel = kernel
        self.fired = 0
        self._failure: BaseException | None = None

    def now(self) -> float:
        """The kernel clock's time in seconds."""
        return self.kernel.clock.now()

    def every(self, period: float, fn: Callable[[], None]) -> Timer:
        """Call ``fn`` on the kernel thread at now+period, now+2*period, ... (no drift) until
        the returned timer is cancelled. Raises KernelError for a period that is not > 0."""
        if not period > 0:
            raise KernelError(f"KernelScheduler.every: period must be > 0 s, got {period!r}")

        def tick() -> None:
            self.fired += 1
            try:
                fn()
            except Exception as exc:
                if self._failure is None:
                    self._failure = exc
                self.kernel.stop()

        return self.kernel.every(period, tick)

    def run_until(self, when: float) -> int:
        """Run the kernel on this thread until clock time ``when`` (on a virtual clock also
        until nothing more can happen); return how many callbacks armed here ran meanwhile.
        As with :class:`~chcos.apps.nbs.scheduling.VirtualScheduler`, a timer due within 1 ns after
        ``when`` counts as due (``k * period`` rounds). Raises KernelError if the kernel already
        runs or a callback failed."""
        before = self.fired
        self.kernel.run(until=when + _EPSILON)
        failure, self._failure = self._failure, None
        if failure is not None:
            raise KernelError(f"NBS cycle failed at {self.now():.6f} s: "
                              f"{type(failure).__name__}: {failure}") from failure
        return self.fired - before

    def run_for(self, seconds: float) -> int:
        """:meth:`run_until` ``now() + seconds``."""
        return self.run_until(self.now() + seconds)


class DevtabIO:
    """The NBS :class:`~chcos.apps.nbs.executor.DeviceIO` on a chcos Devtab (see the module doc).

    ``source`` names the writer in Devtab errors and logs. A failed or stale sensor still reads
    as its last value: the NBS design has no notion of sensor failure (that is part of what CHC
    adds), so the baseline is not given one.
    """

    def __init__(self, devtab: Devtab, source: str = "nbs") -> None:
        self.devtab = devtab
        self.source = source

    def read(self, name: str) -> object | None:
        """The last reading of sensor ``name`` (None before the first). Raises DeviceError for
        an unknown device or an actuator."""
        e = self.devtab.get(name)
        if not e.is_sensor:
            raise DeviceError(f"NBS read of {name}: it is an actuator, not a sensor")
        return e.value if e.readings else None

    def write(self, name: str, value: object) -> None:
        """Command actuator ``name`` through Devtab.write. Raises DeviceError as Devtab does."""
        self.devtab.write(name, value, source=self.source)

    def arrived(self, name: str) -> float | None:
        """When the current reading of sensor ``name`` landed in Devtab (kernel clock), None
        before the first. Raises DeviceError for an unknown device."""
        e = self.devtab.get(name)
        return e.updated_at if e.is_sensor and e.readings else None

    def io(self) -> DeviceIO:
        """This object as the executor's DeviceIO record."""
        return DeviceIO(read=self.read, write=self.write, arrived=self.arrived)


@dataclass
class NbsOnSystem:
    """An NBS executor wired to a System's kernel and Devtab."""

    executor: NbsExecutor
    scheduler: KernelScheduler
    io: DevtabIO

    def start(self) -> None:
        """Arm the executor's cycle on the kernel. Raises KernelError if already started."""
        self.executor.start()

    def stop(self) -> None:
        """Disarm the cycle."""
        self.executor.stop()


def attach(kernel: Kernel, devtab: Devtab, levels: Sequence[Level], *,
           period: float = DEFAULT_PERIOD,
           reactions: Mapping[str, Iterable[str]] | None = None,
           source: str = "nbs") -> NbsOnSystem:
    """An NBS executor for ``levels`` on ``kernel`` (a System's ``kernel``) and ``devtab`` (its
    ``devtab``), cycling every ``period`` seconds once started. ``reactions`` as for
    :class:`~chcos.apps.nbs.executor.NbsExecutor`. Raises KernelError for no levels or a bad
    period."""
    sched = KernelScheduler(kernel)
    dio = DevtabIO(devtab, source)
    ex = NbsExecutor(levels, dio.io(), sched, period=period, reactions=reactions)
    return NbsOnSystem(ex, sched, dio)
