"""Casting rays at a scene: first hits on the CPU with Embree 4 (instances of trees, then of
leaves) or on CUDA with NVIDIA Warp, and the hits labelled by class, prim and tree.

Reads :mod:`usdforest.sensors.scene`; knows nothing of the instruments that fire the rays."""
