"""The member side of an evolver's population, what learners, actors and replays run to take part in
one: joining it, a learner's folder and identity, the config a learner's group runs with and the
assignments of actors and replays (population.py), and a learner's live link with its evolver:
heartbeats, returns, CEM samples, retirement (link.py). The evolver itself is ds/evolver/."""
