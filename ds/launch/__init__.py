"""Launching roles: composing a role from the config (roles.py, role_context.py), the `local`
launcher and its summary (local.py, local_summary.py), and Kubernetes naming (k8s.py)."""
