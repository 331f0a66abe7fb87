"""Dashboard assets; a package so that the package-data rules ship them in the wheel."""
