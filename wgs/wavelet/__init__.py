"""Orthonormal Haar wavelets (the subbands' EXR files are written by `wgs.io.exr`)."""

from .haar import dwt2, idwt2

__all__ = ["dwt2", "idwt2"]
