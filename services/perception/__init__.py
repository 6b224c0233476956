"""``wavegrasp perception``: from raw underwater point clouds to the object's centroid and mesh."""
