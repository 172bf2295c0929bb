"""3D Gaussian splatting: parameters, projection, rasterization, densification, training."""
