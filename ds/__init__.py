"""The network: gRPC/ZeroMQ implementations of algorithm's interfaces and the role processes.

``ds`` is ``algorithm`` plus a network (ARCHITECTURE.md 1): it may import ``algorithm``, ``envs``
and ``protos``; nothing in ``algorithm`` imports it.
"""
