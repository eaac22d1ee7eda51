"""modbus - the ``modbus-tcp`` and ``modbus-rtu`` bus drivers, as composed parts:

* :mod:`drivers.modbus.config` - the plan made once of the typed options and devices (the
  map's keys are :mod:`drivers.codecs.modbus_options`);
* :mod:`drivers.modbus.transactions` - the sans-IO matching of answers to requests;
* :mod:`drivers.modbus.transport` - TCP, serial RTU and an in-process slave, on a worker thread;
* :mod:`drivers.modbus.link` - what is a connection-level cause, units that stop answering;
* :mod:`drivers.modbus.requests` - the jobs and what their answers mean for the devices;
* :mod:`drivers.modbus.engine` - the worker thread, or the kernel thread on virtual time;
* :mod:`drivers.modbus.driver` - the two kinds, each a :class:`drivers.base.Driver` owning them.

The driver classes are imported from here on first use (``from drivers.modbus import
ModbusTcpDriver``), so that the pure parts load without the transports. What the buses do
under faults: ``docs/modbus-faults.md``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from drivers.modbus.driver import ModbusRtuDriver, ModbusTcpDriver

__all__ = ["ModbusRtuDriver", "ModbusTcpDriver"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from drivers.modbus import driver

        return getattr(driver, name)
    raise AttributeError(f"module 'drivers.modbus' has no attribute {name!r}")
