"""Ground station: sample log -> point cloud -> fitted surface -> volume report."""
