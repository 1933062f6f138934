"""usdforest's template library, shipped as package data (``usdforest.templates``).

``cad/`` holds the CAD sources, made by ``make_cad.py``; ``*.usdc`` are the template layers
derived from them by ``usdforest template build pipelines/templates.toml``.
"""
