"""Repair networks (one per file), the diffusion scheduler, and their safetensors storage."""
