"""File formats: scans, trajectories, plane problems and maps."""
