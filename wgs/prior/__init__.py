"""The repair prior: an object corpus rendered by our own code, real coarse-3DGS corruptions of it,
and the pretrained D and U that `wgs finetune` starts from (weights shipped in `weights/`)."""

from pathlib import Path

# the shipped prior: D/ and U/ (config.json + model.safetensors) and provenance.json
WEIGHTS = Path(__file__).parent / "weights"
