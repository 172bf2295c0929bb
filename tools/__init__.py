"""Tools around wgs, beside the package and outside its wheel: benchmarks (`python -m tools.bench`)
and the interruption stress loops (`python -m tools.stress`). They import wgs; wgs never imports
them. Run them from the repository's root."""
