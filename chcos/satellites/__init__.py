"""satellites - layer 8: one CHC-OS system spread over satellite processes (thesis section 6.4)
and the development host that installs, sets priorities and invokes over the link; the system
file that names them.

:mod:`~chcos.satellites.satellite` is one machine's process, :mod:`~chcos.satellites.installlog`
its replicated install log, :mod:`~chcos.satellites.control` the typed requests a host sends it,
:mod:`~chcos.satellites.host` the development host, :mod:`~chcos.satellites.sysfile` the system
file.
"""
