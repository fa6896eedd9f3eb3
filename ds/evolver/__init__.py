"""The evolver role: its composition (role.py), its loop (evolver.py), gRPC server and client (service.py,
client.py), learner registry and assignment (registry.py, assign.py) and persisted state (state.py). What
learners, actors and replays run to take part in its population is ds/member/."""
