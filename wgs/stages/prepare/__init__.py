"""The prepare stage: a scene imported into the workspace (`settings.py`: its settings, facts and
cost; `run.py`: its run)."""
