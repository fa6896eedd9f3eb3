"""The evolver role: its composition (role.py), its loop (evolver.py), gRPC server and client (service.py,
client.py), learner registry and assignment (registry.py, assign.py), persisted state (state.py), the
population of a local run (population.py), and the learner's side of the link (link.py)."""
