"""streaklab: the command-line front end tying drivers, capture, reconstruction and decomposition together."""
from core.provenance import __version__  # noqa: F401
