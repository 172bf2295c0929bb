"""The coarse stage: G_c and the ensemble's members (`settings.py`: its settings, facts and cost;
`run.py`: its run)."""
