"""Where trees stand: point processes (Lewis-Shedler thinning), cell-by-cell sampling,
stand structure (DBH, heights), rasters and the ground's height field."""
