"""The eval stage: the models scored on the test views and the report (`settings.py`: its
settings, facts and cost; `run.py`: its run; `scoring.py`, `shape.py`, `report.py`, `html.py`:
its parts)."""
