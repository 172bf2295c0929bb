"""The priors: an object corpus rendered by our own code, real coarse-3DGS corruptions of it, the
pretrained D and U that `wgs finetune` starts from, and the silhouette model S and volume model V
that carve the visual hull (their weights are shipped in `wgs/weights/`)."""
