"""CAD templates: importing parts with trimesh, decomposing whole-tree models, tube
skeletons, texture coordinates and the template library."""
