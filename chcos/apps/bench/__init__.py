"""bench - the systems and helpers that measure chcos against the thesis (section 6.4).

:mod:`chcos.apps.bench.stats` percentiles and summaries of latency samples;
:mod:`chcos.apps.bench.fig66`
the figure 6.6 system as a CHC system and as the NBS baseline on identical devices and load,
task-execution counts and reaction latencies; :mod:`chcos.apps.bench.emergency` the emergency
reaction under CAN load and the memory soak; :mod:`chcos.apps.bench.svg` the latency plot.
``tools/bench_suite.py`` runs them all and writes ``docs/perf/``.
"""
