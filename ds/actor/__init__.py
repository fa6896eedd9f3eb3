"""The actor role: its composition (role.py), its loop (actor.py) and its replay traffic, inserts with
back-pressure (sink.py)."""
