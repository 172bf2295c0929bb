"""wgs: sparse-view 3D Gaussian object reconstruction (WaveletGaussian)."""

__version__ = "0.1.0"

from .threads import set_runtime_defaults as _set_runtime_defaults

_set_runtime_defaults()  # before torch or numba start their thread pools (see threads.py)
