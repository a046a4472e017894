"""lampsam.evaluation."""
