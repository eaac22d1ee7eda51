"""netutil - loopback helpers shared by the tests: a free TCP port
(:func:`chcos.helpers.free_port`), a unique virtual-CAN channel."""

from __future__ import annotations

import itertools
import os

from chcos.helpers import free_port

_counter = itertools.count()


def unique_channel(prefix: str = "t") -> str:
    """A python-can ``virtual`` channel name no other test in this process uses."""
    return f"{prefix}-{os.getpid()}-{next(_counter)}"


__all__ = ["free_port", "unique_channel"]
