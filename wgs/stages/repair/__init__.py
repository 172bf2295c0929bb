"""The repair stage: pseudo references at novel poses and the carved visual hull (`settings.py`:
its settings, facts and cost; `run.py`: its run)."""
