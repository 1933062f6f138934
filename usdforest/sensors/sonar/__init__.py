"""Bat-like sonar: leaves, wood and ground as reflectors, their backscatter, and the band
sums of the coherent echo.

Built on :mod:`usdforest.sensors.cast` and :mod:`usdforest.sensors.scene`."""
