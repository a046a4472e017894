"""lampsam.frontend."""
