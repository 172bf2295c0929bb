"""The baseline stage: plain 3DGS for the method's training time (`settings.py`: its settings,
facts and cost; `run.py`: its run)."""
