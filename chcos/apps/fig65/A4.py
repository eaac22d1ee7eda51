"""A4 - the system's terminal and log driver on /dev/tty0 and 'log' (figure 6.5)."""

from chcos.system.provided import terminal_log as main

__all__ = ["main"]
