"""viewer - the hierarchy of tasks drawn live: SVG/dot rendering, a snapshot feed, a web page.

Thesis section 6.3 asks for "a program in Unix which will read sysfile.map and output a real-time
graphic representation of the hierarchy of tasks". :mod:`chcos.viewer.layout` lays the map out by
level and :mod:`chcos.viewer.graph` draws it as SVG (without graphviz) or as graphviz dot;
:mod:`chcos.viewer.snapshot` turns a running :class:`~chcos.system.embedded.System` into JSON
snapshots with message rates and an event log; :mod:`chcos.viewer.server` serves them to a
browser page (``chcos view``) and :mod:`chcos.viewer.commands` takes setpri and invoke commands
back; :mod:`chcos.viewer.cli` holds ``chcos map`` and ``chcos view`` (its ``--example`` systems
come from the command line, :mod:`chcos.cli.view`).
"""

from __future__ import annotations

from chcos.errors import ChcosError


class ViewerError(ChcosError):
    """The viewer could not start (address in use, bad map) or a snapshot could not be taken."""


__all__ = ["ViewerError"]
