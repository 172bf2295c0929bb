"""Shape: the visual hull as an occupancy grid, its silhouettes at any camera, silhouette scores,
the leave-one-out estimate of how fat the hull is, and carving the hull with predicted silhouettes."""
