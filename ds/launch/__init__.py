"""Launching roles: what every role is given (role_context.py; each role's composition lives in its own
package, ds/<role>/role.py), the `local` launcher and its summary (local.py, local_summary.py), and
Kubernetes naming (k8s.py)."""
