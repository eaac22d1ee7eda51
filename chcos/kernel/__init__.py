"""kernel - layer 2 of thesis section 6.1.2: the priority scheduler that steps task coroutines
(context switch, ready/suspend/wait/sleep, resched by priority), its timers and interrupt queue,
the injected clock, semaphores (the memory manager's part Python does not already do) and the
instrumentation hooks.
"""
