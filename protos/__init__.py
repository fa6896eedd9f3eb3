"""Protocol buffers of the network roles: ``*.proto`` (the API documentation) and the code generated
from them (``*_pb2.py``, ``*_pb2_grpc.py``, ``*_pb2.pyi``), committed so that no build step is needed.

Regenerate after editing a ``.proto`` with ``python -m protos.generate`` from the repository root;
tests/protos/test_generate.py fails while the committed code is stale.
"""
