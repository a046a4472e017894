"""lampsam.localization."""
