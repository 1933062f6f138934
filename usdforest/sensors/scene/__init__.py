"""The scene a sensor sees: a composed stage's world-space triangles, leaves and instances
as plain arrays (:func:`~usdforest.sensors.scene.extraction.extract_scene`), the stage's
frame and time, its animation, and the on-disk cache of what each prototype holds.

Reads stages; knows nothing of rays or instruments."""
