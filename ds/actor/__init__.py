"""The actor role: its loop (actor.py) and its replay traffic, inserts with back-pressure (sink.py)."""
