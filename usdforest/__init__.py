"""usdforest: trees from L-systems and CAD templates, forests from inhomogeneous Poisson
processes, written as OpenUSD layers."""

__all__ = ["__version__"]


def __getattr__(name: str) -> str:
    # looked up lazily: importing importlib.metadata costs start-up time, and a Ctrl-C during
    # start-up should land in the command's own handler (usdforest.entry)
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("usdforest")
        except PackageNotFoundError:  # a source tree that is not installed
            return "0.0.0+source"
    raise AttributeError(name)
