"""Provenance shared by every store and file the package writes: the software version."""
from importlib import metadata as _metadata

__all__ = ["__version__"]

try:
    __version__ = _metadata.version("streaklab")
except _metadata.PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.1.0+src"
