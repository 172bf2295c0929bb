"""Orthonormal Haar wavelets and subband EXR files."""

from .haar import dwt2, idwt2

__all__ = ["dwt2", "idwt2"]
