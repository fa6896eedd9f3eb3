"""The SAC math: the acting policy (policy.py) and the learner that extends it (learner.py), what one
update computes (losses.py: plain SAC, composed with the features of features.py, over the window of
window.py and the learner's parts of parts.py) from the pure loss functions (equations.py) and the
n-step and V-trace targets (returns.py), the learner's checkpoint state and optimizers (checkpoint_state.py), the
schedules of learning rate and coefficients (schedules.py), the checks of a batch against the task
(batch_checks.py) and the update replayed as a CUDA graph (update_graph.py)."""
