"""Everything that runs inside one process: models, losses, replay, actor and learner loops.

Imports nothing of ours outside ``algorithm``, and nothing here knows about sockets
(docs/architecture.md sections 1 and 2).
"""
