"""serving - what the north-side services (:mod:`chcos.north`) and the live view
(:mod:`chcos.viewer`) share, below both: who may see and command (:mod:`chcos.serving.auth`:
users, roles, password hashes, the login throttle), the bounds every north-side server keeps
(:mod:`chcos.serving.guard`: connections, request sizes and times, library logs) and an asyncio
loop on a thread of its own that serves a running system (:mod:`chcos.serving.loopthread`).
Neither imports the other through it, so the services may start the viewer without a circle."""
