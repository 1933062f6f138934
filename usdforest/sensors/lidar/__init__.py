"""Laser scanners: scan patterns and their settings, pulses cast as diverging beams, the
echoes a scanner reports, and GPS time as LAS stores it.

Built on :mod:`usdforest.sensors.cast`."""
