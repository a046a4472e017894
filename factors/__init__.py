"""lampsam.factors."""
