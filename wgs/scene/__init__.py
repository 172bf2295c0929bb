"""Scene import: every supported format becomes `RawScene` (OpenCV world-to-camera + K)."""
