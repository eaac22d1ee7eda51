"""A3 - the system's file sampler on 'testfile' (figure 6.5)."""

from chcos.system.provided import file_sampler as main

__all__ = ["main"]
