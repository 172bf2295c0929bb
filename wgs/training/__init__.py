"""Training of the networks (D, U, S): one loop (`loop.fit`) and each network's objective, used by
the per-object stage (`wgs finetune`) and by the prior's pretraining (`python -m tools.prior`)."""
