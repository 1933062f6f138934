"""usdforest: trees from L-systems and CAD templates, forests from inhomogeneous Poisson
processes, written as OpenUSD layers.

From Python (see :mod:`usdforest.api`)::

    import usdforest

    recipe = usdforest.load_recipe("stand-1ha", seed=7)
    built = usdforest.build_forest(recipe, "stand.usda")
    shot = usdforest.scan("stand.usda", "lidar", (50, 50, 2))
"""

__all__ = [
    "__version__",
    "build_forest",
    "fly",
    "grow_tree",
    "load_recipe",
    "recipes",
    "scan",
    "survey",
]
_API = frozenset(__all__) - {"__version__"}


def __getattr__(name: str):
    # looked up lazily: importing importlib.metadata or numpy costs start-up time, and a Ctrl-C
    # during start-up should land in the command's own handler (usdforest.entry)
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("usdforest")
        except PackageNotFoundError:  # a source tree that is not installed
            return "0.0.0+source"
    if name in _API:
        from usdforest import api

        return getattr(api, name)
    raise AttributeError(name)


def __dir__() -> list[str]:
    return sorted(__all__)
