"""The configuration: the typed schema of every section and its defaults (schema.py, written out in
default_config.yaml), the layering of defaults, task file and overrides into one validated config
(load.py), the reading of the original project's task files (original.py) and the ``random_params``
draws (random_params.py)."""
