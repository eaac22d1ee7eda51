"""resources - the files chcos ships as package data (device maps, DBC/EDS files, install scripts,
the viewer's pages), found with :mod:`importlib.resources` wherever chcos is installed.

A regular install (``pip install .``) and a source checkout both keep these files on disk; the
loaders need real paths because a device map names its DBC/EDS files relative to itself, so
:func:`path` hands out a :class:`pathlib.Path` and refuses an install that is not on disk (a
zipped import) with a clear error rather than failing later on a missing file.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from chcos.errors import ChcosError

__all__ = ["path"]


def path(package: str, *parts: str) -> Path:
    """The on-disk path of ``parts`` inside ``package`` (a dotted package name).

    Raises :class:`ChcosError` when the package is not installed on disk or the file is absent
    (naming the package and the file)."""
    root = files(package)
    where = Path(str(root))
    if not where.is_dir():
        raise ChcosError(f"package data of {package}: {where} is not a directory on disk "
                         f"(chcos must be installed unpacked, e.g. pip install .)")
    target = where.joinpath(*parts)
    if not target.exists():
        raise ChcosError(f"package data of {package}: {'/'.join(parts)} is missing from "
                         f"{where} (a broken install?)")
    return target
