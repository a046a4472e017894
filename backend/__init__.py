"""lampsam.backend."""
