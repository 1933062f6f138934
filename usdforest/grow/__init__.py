"""Growing one tree: L-systems, the turtle, skeletons, species presets and allometry, and
the placement of templates, colliders and proxies on the skeleton (numpy, no USD)."""
