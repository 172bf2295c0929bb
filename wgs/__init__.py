"""wgs: sparse-view 3D Gaussian object reconstruction (WaveletGaussian)."""

__version__ = "0.1.0"
