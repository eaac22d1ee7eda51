"""describe - the one-line text of a task's abnormal completion: the error and where in the
task's own code it happened (frames of chcos' OS, the drivers, the standard library and
installed packages are skipped)."""

from __future__ import annotations

import os
import sysconfig
import traceback

_OS_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))   # chcos/
_APPS_DIR = os.path.join(_OS_DIR, "apps") + os.sep
_DRIVERS_DIR = os.path.join(os.path.dirname(_OS_DIR), "drivers") + os.sep
_LIB_DIRS = tuple(os.path.abspath(p) for p in {sysconfig.get_path("stdlib"),
                                               sysconfig.get_path("platstdlib"),
                                               sysconfig.get_path("purelib"),
                                               sysconfig.get_path("platlib")} if p)


def _library_frame(filename: str) -> bool:
    """True for a frame in chcos' own OS modules (not the applications under chcos/apps), the
    drivers, the standard library or an installed package: not where a task's bug is."""
    path = os.path.abspath(filename)
    in_os = path.startswith(_OS_DIR + os.sep) and not path.startswith(_APPS_DIR)
    return (in_os or path.startswith(_DRIVERS_DIR) or path.startswith(_LIB_DIRS)
            or filename.startswith("<frozen "))


def describe_error(exc: BaseException) -> str:
    """The text of a task's abnormal completion: ``Type: message (file:line)``, the file and
    line being the innermost frame of the task's own code that the exception passed through
    (the innermost frame at all if none is the task's), e.g.
    ``NameError: name 'vaule' is not defined (A1.py:12)``."""
    text = f"{type(exc).__name__}: {exc}"
    frames = traceback.extract_tb(exc.__traceback__) if exc.__traceback__ is not None else []
    if not frames:
        return text
    own = [f for f in frames if not _library_frame(f.filename)]
    where = (own or frames)[-1]
    return f"{text} ({os.path.basename(where.filename)}:{where.lineno})"
