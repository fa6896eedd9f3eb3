"""The learner role: its composition (role.py), its loop (learner.py), the gRPC service actors register
with and fetch weights from (service.py), and its replay traffic: prefetched batches, priority updates
(feeds.py)."""
