"""lampsam.datasets."""
