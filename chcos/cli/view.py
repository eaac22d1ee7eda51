"""view - ``chcos view`` with the applications' example systems (``--example fig65``).

The viewer (:mod:`chcos.viewer.cli`, layer 9) knows no application; the command line may, so it
hands the viewer the builders of the examples it can show (:data:`EXAMPLES`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from chcos.viewer.cli import Example, ExampleBuilder
from chcos.viewer.cli import view_main as _view_main

if TYPE_CHECKING:
    from chcos.kernel.clock import Clock
    from chcos.viewer.server import Viewer


def fig65(clock: Clock, workdir: Path) -> Example:
    """The figure 6.5 system of section 6.1.5, installed by the thesis' script, C1 invoked."""
    from chcos.apps import fig65 as app
    from chcos.apps.fig65.runner import build

    return Example(build(clock, workdir), app.SCRIPT, ["C1"])


EXAMPLES: dict[str, ExampleBuilder] = {"fig65": fig65}
"""The example systems ``chcos view --example NAME`` can build."""


def view_main(argv: Sequence[str], *, stop: threading.Event | None = None,
              on_ready: Callable[[Viewer], None] | None = None, out: TextIO | None = None
              ) -> int:
    """``chcos view`` (see :func:`chcos.viewer.cli.view_main`) with :data:`EXAMPLES`."""
    return _view_main(argv, examples=EXAMPLES, stop=stop, on_ready=on_ready, out=out)
