"""commands - the checks of an actuator command before it reaches a driver: a number where the
bus carries numbers, finite, inside the device's limits (refused, never clamped), scaled to its
raw value, and accepted by the driver's own ``check_value`` (the address type's range)."""

from __future__ import annotations

import math
import sys
from typing import Any

from chcos.devices.entry import DeviceEntry, NumberCheck, scalable
from chcos.devices.table import DeviceTable
from chcos.errors import DeviceError

#: An integer command beyond this magnitude has no float (refused as not finite).
_BIG = int(sys.float_info.max)
#: The largest finite float: the bounds of an unlimited device's range (see NumberCheck).
_FMAX = sys.float_info.max


class CommandChecks:
    """Command checks for :class:`chcos.devices.devtab.Devtab`, which owns one; ``table`` says
    which devices are local (only a local device's driver is asked about a value)."""

    def __init__(self, table: DeviceTable) -> None:
        self._table = table

    def check(self, e: DeviceEntry, value: Any, source: str) -> Any:
        """The raw value for command ``value`` from ``source`` to ``e``; raises DeviceError
        naming the device, the value and the rule (counted as rejected) if refused."""
        kind = type(value)
        if kind is int or kind is float:
            # the common case, the same rules in fewer steps: a plain number inside what the
            # limits and the driver accept (see NumberCheck), raw = value as a float (as
            # (value - 0) / 1 gives); everything else, and every refusal, is _check_any's
            c = e.number_check
            if c is None or c.driver is not e.driver:
                c = self._number_check(e)
            if c.lo <= value <= c.hi and (kind is int or not c.integral or value.is_integer()):
                raw = float(value)
                ask = c.ask
                if ask is None or ask(e.spec.name, raw) is None:
                    return raw
        return self._check_any(e, value, source)

    def _number_check(self, e: DeviceEntry) -> NumberCheck:
        """Make ``e``'s :class:`NumberCheck` for its current driver (from the device's limits
        and the driver's :meth:`~chcos.devices.driver.Driver.accepts`) and keep it in
        ``e.number_check``; the one place it is written."""
        spec, drv = e.spec, e.driver
        if spec.scale != 1 or spec.offset != 0 or spec.round:
            c = NumberCheck(drv, 1.0, 0.0, False, None)
        else:
            lo_, hi_ = spec.limits
            lo = -_FMAX if lo_ is None else max(float(lo_), -_FMAX)
            hi = _FMAX if hi_ is None else min(float(hi_), _FMAX)
            integral = False
            ask = None
            if drv is not None and self._table.is_local(spec.machine):
                acc = drv.accepts(spec.name)
                if acc is None:
                    ask = drv.check_value
                else:
                    lo, hi, integral = max(lo, acc[0]), min(hi, acc[1]), acc[2]
            c = NumberCheck(drv, lo, hi, integral, ask)
        e.number_check = c
        return c

    def _check_any(self, e: DeviceEntry, value: Any, source: str) -> Any:
        """:meth:`check` for every value (the refusals and their reasons)."""
        spec = e.spec
        device = e.name
        # a bus that carries numbers only (every field bus); memory actuators may hold any value
        numeric = spec.round or (e.driver is not None and e.driver.numeric_only)
        if isinstance(value, bool):
            value = int(value)
        num = scalable(value)
        if numeric and not num:
            e.rejected += 1
            raise DeviceError(f"command {value!r} from {source} to {device}: expected a number "
                              f"({spec.units or 'engineering units'})")
        if num and not (-_BIG <= value <= _BIG if isinstance(value, int) else math.isfinite(value)):
            e.rejected += 1
            raise DeviceError(f"command {value!r} from {source} to {device}: expected a finite "
                              f"number")
        lo, hi = spec.limits
        if num and ((lo is not None and value < lo) or (hi is not None and value > hi)):
            e.rejected += 1
            raise DeviceError(
                f"command {value!r} {spec.units} from {source} to {device} is outside its limits "
                f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]")
        raw = (value - spec.offset) / spec.scale if num else value
        if scalable(raw):
            if not math.isfinite(raw):
                e.rejected += 1
                raise DeviceError(f"command {value!r} from {source} to {device}: raw value "
                                  f"{raw!r} (scale/offset) is not a finite number")
            if spec.round:
                raw = round(raw)
            elif isinstance(raw, float) and raw.is_integer() is False:
                near = round(raw)
                if abs(raw - near) <= 1e-9 * max(1.0, abs(raw)):
                    raw = float(near)   # only scale/offset arithmetic noise
        if e.driver is not None and self._table.is_local(spec.machine):
            why = e.driver.check_value(device, raw)
            if why is not None:
                e.rejected += 1
                raise DeviceError(f"command {value!r} from {source} to {device} refused: raw "
                                  f"value {raw!r}: {why}"
                                  + ("" if spec.round else " (a device with round = true rounds "
                                                           "to an integer)"))
        return raw
