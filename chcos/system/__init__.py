"""system - layer 7, the system manager (TSK0) of thesis section 6.1.2: install, setpri and
invoke with the host's command syntax (section 6.3), the hierarchy rules, ``sysfile.map``, the
system-provided driver tasks (section 6.1.5), and :class:`chcos.system.embedded.System`, the
composition root of one satellite.
"""
