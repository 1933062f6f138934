"""Optical instruments: the pinhole camera (depth, segmentation, shaded RGB) and canopy
gap fractions measured by parallel rays.

Built on :mod:`usdforest.sensors.lidar` (the depth camera's settings) and
:mod:`usdforest.sensors.cast`."""
