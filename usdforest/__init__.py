"""usdforest: trees from L-systems and CAD templates, forests from inhomogeneous Poisson
processes, written as OpenUSD layers."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("usdforest")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+source"

__all__ = ["__version__"]
