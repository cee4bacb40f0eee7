"""The data layer's error base class.

Every error the library raises for input the user can fix (a bad configuration, a path that is
not a usable store, a calibration that does not fit, settings a run cannot resume with)
derives from :class:`StreaklabError`, so a caller catches them all at once.  Each subclass also
keeps its built-in base (``ValueError``; ``RuntimeError`` for capture failures; ``FileExistsError``
for an occupied output path).  The device
drivers keep their own base, :class:`drivers.errors.DriverError`.
"""

__all__ = ["StreaklabError", "OutputExistsError"]


class StreaklabError(Exception):
    """An error in the data the library was given; its message says exactly what and where."""


class OutputExistsError(StreaklabError, FileExistsError):
    """An output path is already taken and replacing it was not asked for.

    ``path`` (when given) names it, so that a command can word the error its own way
    ("pass --overwrite") instead of the library's ("pass overwrite=True").
    """

    def __init__(self, message, path=None):
        super().__init__(message)
        self.path = None if path is None else str(path)
