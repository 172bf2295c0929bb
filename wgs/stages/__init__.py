"""Pipeline stages: one package per stage, `stages/<name>/`, holding its settings, its facts for the
registry and its cost model (`settings.py`, light) and its run (`run.py`, which loads the library
on first use); `registry.py` lists them in order, `stage.py` says what a stage is, `shared.py`
holds what the runs share."""
