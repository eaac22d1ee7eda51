"""netutil - loopback helpers shared by the tests: a free TCP port, a unique virtual-CAN channel."""

from __future__ import annotations

import itertools
import os
import socket

_counter = itertools.count()


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bind to port 0, read it back)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def unique_channel(prefix: str = "t") -> str:
    """A python-can ``virtual`` channel name no other test in this process uses."""
    return f"{prefix}-{os.getpid()}-{next(_counter)}"
