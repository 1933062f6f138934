"""Data shipped with the package (the default pipeline)."""
