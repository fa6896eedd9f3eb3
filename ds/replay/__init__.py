"""The replay role: its composition and loop (role.py), the gRPC server and client of the replay table
(service.py), the encoding of chunks, batches and info (codec.py), and the snapshot files it owns
(files.py)."""
