"""codecs - the pure half of the bus drivers: coding and checking that needs no bus.

One module per protocol family (:mod:`~drivers.codecs.can`, :mod:`~drivers.codecs.serial`,
:mod:`~drivers.codecs.modbus` with the Modbus map keys :mod:`~drivers.codecs.modbus_options` and
the in-process hand-off point :mod:`~drivers.codecs.modbus_direct`,
:mod:`~drivers.codecs.canopen`). None imports I/O (a bus library,
socket, thread or event loop; ``vcan_tests/test_layers.py`` enforces it), so the drivers and the
simulated slaves share them without the simulators depending on a driver's threads.
"""
