"""north - the north side of the gateway: what reaches a running system from above.

:mod:`chcos.north.metrics` (Prometheus), :mod:`chcos.north.modbus_facade` (a Modbus TCP server
over the device table), :mod:`chcos.north.opcua` (an OPC UA server), the live view
(:mod:`chcos.viewer`), and who may command through them (:mod:`chcos.north.auth`). Device health
is read through :mod:`chcos.north.health` only. :mod:`chcos.north.services` starts them from a
running system (``chcos run --metrics --modbus-facade --opcua --view``).
"""

from __future__ import annotations

from chcos.errors import ChcosError


class NorthError(ChcosError):
    """A north-side service could not start (address in use, TLS missing, bad map or users)."""


__all__ = ["NorthError"]
