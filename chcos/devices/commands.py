"""commands - the checks of an actuator command before it reaches a driver: a number where the
bus carries numbers, finite, inside the device's limits (refused, never clamped), scaled to its
raw value, and accepted by the driver's own ``check_value`` (the address type's range)."""

from __future__ import annotations

import math
import sys
from typing import Any

from chcos.devices.entry import DeviceEntry, scalable
from chcos.devices.health import DeviceHealth
from chcos.errors import DeviceError

#: An integer command beyond this magnitude has no float (refused as not finite).
_BIG = int(sys.float_info.max)


class CommandChecks(DeviceHealth):
    """Command checks for :class:`chcos.devices.devtab.Devtab` (its base class)."""

    def _check_command(self, e: DeviceEntry, value: Any, source: str) -> Any:
        """The raw value for ``value``; raises DeviceError (counted as rejected) if refused."""
        spec = e.spec
        kind = type(value)
        if (kind is float or kind is int) and spec.scale == 1 and spec.offset == 0 \
                and not spec.round:
            # the common case, the same rules in fewer steps: a plain finite number inside the
            # limits, raw = value (as a float, as (value - 0) / 1 gives), the driver's check
            lo, hi = spec.limits
            raw = float(value) if kind is float or -_BIG <= value <= _BIG else math.inf
            if raw - raw == 0 and (lo is None or value >= lo) and (hi is None or value <= hi):
                drv = e.driver
                local = self._local   # self.is_local(spec.machine), inlined
                if drv is None or (local is not None and spec.machine not in local) \
                        or drv.check_value(spec.name, raw) is None:
                    return raw
        return self._check_any(e, value, source)

    def _check_any(self, e: DeviceEntry, value: Any, source: str) -> Any:
        """:meth:`_check_command` for every value (the refusals and their reasons)."""
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
        if e.driver is not None and self.is_local(spec.machine):
            why = e.driver.check_value(device, raw)
            if why is not None:
                e.rejected += 1
                raise DeviceError(f"command {value!r} from {source} to {device} refused: raw "
                                  f"value {raw!r}: {why}"
                                  + ("" if spec.round else " (a device with round = true rounds "
                                                           "to an integer)"))
        return raw
