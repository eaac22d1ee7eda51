"""hil - evidence from hardware-in-the-loop runs: which device states a cell's tests reached
(:mod:`chcos.hil.coverage` against :mod:`chcos.hil.catalogue`), the trace of a run
(:mod:`chcos.hil.trace`) and what two traces disagree on (:mod:`chcos.hil.diff`), all observed
through :mod:`chcos.hil.observe`; docs/hil-evidence.md describes them."""
