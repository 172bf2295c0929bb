"""The mask-data stage: corrupted/clean LL pairs for the repair models (`settings.py`: its
settings, facts and cost; `run.py`: its run)."""
