"""serving - what the north-side services (:mod:`chcos.north`) and the live view
(:mod:`chcos.viewer`) share, below both: who may see and command (:mod:`chcos.serving.auth`:
users, roles, password hashes) and an asyncio loop on a thread of its own that serves a running
system (:mod:`chcos.serving.loopthread`). Neither imports the other through it, so the services
may start the viewer without a circle."""
