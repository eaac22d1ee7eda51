"""helpers - the small helpers every layer shares (layer 0: imports nothing of chcos).

* :func:`is_int`, :func:`is_number` - the type checks of configuration values, where a TOML or
  JSON ``true`` must not pass for the integer 1;
* :func:`free_port` - a loopback TCP port for a simulator, a test or a benchmark to bind.
"""

from __future__ import annotations

import socket
from typing import Any, TypeGuard


def is_int(value: Any) -> TypeGuard[int]:
    """True if ``value`` is an int and not a bool (``True`` is an int to Python, not to a
    configuration file)."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> TypeGuard[int | float]:
    """True if ``value`` is an int or a float and not a bool."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` (loopback by default; an IPv6 address works too) that was free a
    moment ago: bind to port 0 and read the port back. Another process may take it before the
    caller binds it; use it for simulators, tests and benchmarks, not where the race matters.
    Raises OSError if ``host`` cannot be bound."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])
