"""satellites - layer 8: one CHC-OS system spread over satellite processes (thesis section 6.4)
and the development host that installs, sets priorities and invokes over the link; the system
file that names them.
"""
