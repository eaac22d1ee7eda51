"""helpers - the small helpers every layer shares, kept once here (layer 0: imports only
chcos.errors).

* :func:`is_int`, :func:`is_number` - the type checks of configuration values, where a TOML or
  JSON ``true`` must not pass for the integer 1;
* :func:`free_port` - a loopback TCP port for a simulator, a test or a benchmark to bind;
* :data:`NAME_PATTERN` - the name of a task or device (letters, digits,
  ``_ . -``, not starting with a digit, ``.`` or ``-``);
* :func:`load_toml` - a TOML file read with an error that names the file, what it is and what
  went wrong.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any, TypeGuard

from chcos.errors import ConfigError


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
    return free_ports(1, host)[0]


def free_ports(count: int, host: str = "127.0.0.1") -> list[int]:
    """``count`` distinct TCP ports on ``host`` that were free a moment ago (as
    :func:`free_port`, but all bound at once, so that two of them cannot be the same port, as
    two calls of free_port can be). Raises OSError if ``host`` cannot be bound."""
    import socket  # here, not at the top: the pure codecs import this module, without I/O
    from contextlib import ExitStack

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with ExitStack() as stack:
        socks = [stack.enter_context(socket.socket(family, socket.SOCK_STREAM))
                 for _ in range(count)]
        for sock in socks:
            sock.bind((host, 0))
        return [int(sock.getsockname()[1]) for sock in socks]


#: A task or device name: ``[A-Za-z_][A-Za-z0-9_.-]*`` (use ``fullmatch``).
NAME_PATTERN = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*")


def load_toml(path: str | Path, what: str = "file") -> dict[str, Any]:
    """The document in TOML file ``path`` (``what`` says what it is: "system file", "users
    file"...). Raises ConfigError naming the file: it cannot be read, is not UTF-8, is not
    valid TOML (with tomllib's line and column), or nests too deeply."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read {what}: {exc}") from exc
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: {what} is not valid TOML: {exc}") from exc
    except RecursionError:
        raise ConfigError(f"{p}: {what} nests tables or arrays too deeply") from None
