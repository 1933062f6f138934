"""Sensors on composed stages: scene extraction, lidar ray casting, sonar foliage echoes."""
