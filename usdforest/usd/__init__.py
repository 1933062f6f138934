"""The only package that imports pxr: layers, templates, trees, forests."""
