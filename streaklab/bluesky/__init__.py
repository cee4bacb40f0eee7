"""Bluesky / ophyd-async integration (the optional extra ``streaklab[bluesky]``).

:func:`scan` is a Bluesky plan that performs ``streaklab capture``'s scan from a RunEngine;
:mod:`streaklab.bluesky.devices` holds the ophyd-async devices it builds on the drivers.
Nothing outside this package imports bluesky or ophyd-async.
"""
from .plans import scan

__all__ = ["scan"]
