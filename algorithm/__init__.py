"""Everything that runs inside one process: models, losses, replay, actor and learner loops.

Imports torch, numpy and gymnasium only; nothing here knows about sockets (ARCHITECTURE.md 1).
"""
