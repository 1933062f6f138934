"""usdforest's pipeline recipes, shipped as package data (``usdforest.pipelines``).

``default.toml`` is the embedded default of ``usdforest build``; the others are the paper's
scenarios, stands and benchmarks. See the README for the format.
"""
