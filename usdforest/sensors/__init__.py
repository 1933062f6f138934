"""Sensors on composed stages, in the order data flows through them:

- :mod:`~usdforest.sensors.scene`: what a stage holds, as arrays (triangles, leaves,
  instances, motion);
- :mod:`~usdforest.sensors.cast`: rays cast at a scene (Embree 4 on the CPU, Warp on CUDA);
- :mod:`~usdforest.sensors.lidar`, :mod:`~usdforest.sensors.sonar` and
  :mod:`~usdforest.sensors.optics`: the instruments;
- :mod:`~usdforest.sensors.platforms`: instruments at a pose or along a path.

Each layer imports only the ones above it in this list (and :mod:`~usdforest.sensors.pose`,
which all share); ``tests/test_layout.py`` checks it."""
