"""The network: gRPC/ZeroMQ implementations of algorithm's interfaces and the role processes.

``ds`` is ``algorithm`` plus a network (docs/architecture.md section 1): it may import ``algorithm``
and ``protos``, and ``envs`` only in the role compositions (ds/<role>/role.py); nothing in ``algorithm``
imports it (section 2). Each role's package holds its composition, its loop, its server and its client.
"""
