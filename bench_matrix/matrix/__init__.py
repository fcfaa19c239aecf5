"""The matrix file: its schema (schema.py), loading with located errors (load.py: `load_matrix`), the typed
values it reads into (spec.py) and its expansion into cells (expand.py)."""
