"""common - layer 0: the small helpers several layers share, kept once here.

:data:`NAME_PATTERN` is the name of a task or device (letters, digits, ``_ . -``, not starting
with a digit, ``.`` or ``-``); :func:`load_toml` reads a TOML file with an error that names the
file, what it is and what went wrong.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

from chcos.errors import ConfigError

#: A task or device name: ``[A-Za-z_][A-Za-z0-9_.-]*`` (use ``fullmatch``).
NAME_PATTERN = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*")


def is_name(text: object) -> bool:
    """Whether ``text`` is a valid task or device name (see :data:`NAME_PATTERN`)."""
    return isinstance(text, str) and NAME_PATTERN.fullmatch(text) is not None


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
