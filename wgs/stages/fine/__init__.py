"""The fine stage: G_f trained on the photos and the pseudo references (`settings.py`: its
settings, facts and cost; `run.py`: its run)."""
