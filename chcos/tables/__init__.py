"""tables - layer 1, the system tables of thesis section 6.1.3 and appendix 3: the task table
(Tsktab) and the message table (Msgtab) with its links and input ports (Usrtab). Plain data and
the rules on it; the managers above act on them.
"""
