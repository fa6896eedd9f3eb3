"""The network parts every role uses: gRPC plumbing (rpc.py), the tensor wire format (wire.py),
credentials (security.py) and the ZeroMQ parameter stream with its signing key (params.py, stream_key.py)."""
