"""usrmgr - deprecated alias of :mod:`chcos.user.context`, kept for task code written before the
layered layout (issue 14) that imports ``from chcos.usrmgr import TaskContext``.

Importing it warns (:class:`DeprecationWarning`); new code imports
``from chcos.user.context import TaskContext``. Nothing in chcos itself imports this module
(vcan_tests/test_layers.py checks), and no other old module name has an alias.
"""

from __future__ import annotations

import warnings

from chcos.user.context import Event, TaskContext

__all__ = ["Event", "TaskContext"]

warnings.warn("chcos.usrmgr is deprecated: import TaskContext from chcos.user.context",
              DeprecationWarning, stacklevel=2)
