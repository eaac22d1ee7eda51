"""cli - the ``chcos`` command (top layer): a thin dispatcher to each subcommand's module, and
the commands an integrator runs (run a cell, monitor a live bus, scaffold a project). Only this
layer may start an application of ``chcos.apps``.
"""
