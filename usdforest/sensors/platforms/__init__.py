"""Instruments carried: one scan at a pose, flights along a path, and the checks of a pose
against the scene. What the CLI's ``scan`` and ``fly`` and the Python API call.

The top of the sensors: it uses every instrument; nothing below imports it."""
