"""The priors: an object corpus rendered by our own code, real coarse-3DGS corruptions of it, the
pretrained D and U that `wgs finetune` starts from, and the silhouette model S and volume model V
that carve the visual hull (weights shipped in `weights/`)."""

from pathlib import Path

# the shipped prior: D/ and U/ (config.json + model.safetensors) and provenance.json
WEIGHTS = Path(__file__).parent / "weights"
WEIGHTS_S = WEIGHTS / "S"  # the silhouette model S: config.json, model.safetensors, provenance.json
WEIGHTS_V = WEIGHTS / "V"  # the volume model V: config.json, model.safetensors, provenance.json
