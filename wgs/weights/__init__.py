"""The networks wgs ships, found by path here by the stages that load them and by `tools.prior`,
which builds them (`make prior`, `make shape-prior`). Each folder holds config.json,
model.safetensors and provenance.json (objects, licences, training curves)."""

from pathlib import Path

# the repair prior: D/ (the LL-domain denoiser) and U/ (the HF U-Net), and their provenance.json
WEIGHTS = Path(__file__).parent
WEIGHTS_S = WEIGHTS / "S"  # the silhouette model S
WEIGHTS_V = WEIGHTS / "V"  # the volume model V
