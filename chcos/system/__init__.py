"""system - layer 7, the system manager (TSK0) of thesis section 6.1.2: install, setpri and
invoke with the host's command syntax (section 6.3), the hierarchy rules, ``sysfile.map``, the
system-provided driver tasks (section 6.1.5), and :class:`chcos.system.embedded.System`, the
composition root of one satellite.

:mod:`~chcos.system.manager` is TSK0 (boot, setpri, invoke, task operations, the map document),
:mod:`~chcos.system.installer` its install half, :mod:`~chcos.system.mapfile` paces the map
writes, :mod:`~chcos.system.ports` names what TSK0 needs of the layers below;
:mod:`~chcos.system.cmdline` parses host commands, :mod:`~chcos.system.sysmap` reads and writes
the map, :mod:`~chcos.system.textview` renders it as text, :mod:`~chcos.system.loader` finds task
code, :mod:`~chcos.system.provided` holds tasks A3/A4; :mod:`~chcos.system.affinity` pins a
process to the CPUs its system file names.
"""
