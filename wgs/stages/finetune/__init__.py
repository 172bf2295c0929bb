"""The finetune stage: the repair models D and U fitted to this object (`settings.py`: its
settings, facts and cost; `run.py`: its run)."""
