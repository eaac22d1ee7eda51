"""nbs - the NBS cross-coupled processing hierarchy, run by chcos as the comparison baseline.

Thesis 3.8, 4.1 and 4.3.1: one command (H), sensory (G) and world-model (M) finite-state machine
per level, all executed every 28 ms and talking through common memory. Appendix 1's H tables
are data (``tables/H1.toml`` .. ``H3.toml``, see ``tables/NOTES.md`` for the OCR repairs);
:mod:`chcos.apps.nbs.statetable` loads and interprets them, :mod:`chcos.apps.nbs.executor` runs a
hierarchy cyclically on an injected scheduler, :mod:`chcos.apps.nbs.fig67` is the section-6.4
comparison system.
"""

from chcos.apps.nbs.executor import (
    DEFAULT_PERIOD,
    CommonMemory,
    DeviceIO,
    Latency,
    Level,
    LevelContext,
    Module,
    NbsExecutor,
    Order,
    Report,
    Sample,
    TableH,
)
from chcos.apps.nbs.scheduling import RunnableScheduler, Scheduler, VirtualScheduler
from chcos.apps.nbs.statetable import (
    BUILTIN_TABLES,
    Call,
    Machine,
    StateTable,
    StateTableError,
    Step,
    check_hierarchy,
    load_builtin,
    load_table,
    parse_table,
)

__all__ = [
    "BUILTIN_TABLES",
    "DEFAULT_PERIOD",
    "Call",
    "CommonMemory",
    "DeviceIO",
    "Latency",
    "Level",
    "LevelContext",
    "Machine",
    "Module",
    "NbsExecutor",
    "Order",
    "Report",
    "RunnableScheduler",
    "Sample",
    "Scheduler",
    "StateTable",
    "StateTableError",
    "Step",
    "TableH",
    "VirtualScheduler",
    "check_hierarchy",
    "load_builtin",
    "load_table",
    "parse_table",
]
