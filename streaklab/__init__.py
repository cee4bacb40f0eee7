"""streaklab: the command-line front end tying drivers, capture, reconstruction and decomposition together."""
from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("streaklab")
except _metadata.PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.1.0+src"
