"""The installed package's version, at the bottom of the import graph so every layer may read it."""

from importlib.metadata import PackageNotFoundError, version

__all__ = ["__version__"]

try:
    __version__ = version("kalmansfm")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"
