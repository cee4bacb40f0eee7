"""Counts in messages: ``counted(1, "pixel")`` -> ``"1 pixel"``, ``counted(2, "pixel")`` -> ``"2 pixels"``.

Every message that prints a count of something (pixels, chunks, lines) words it through
:func:`counted`, so that no message reads "1 pixels" and large counts get thousands separators.
"""
from __future__ import annotations

__all__ = ["counted", "plural"]


def plural(n, noun: str, many: str | None = None) -> str:
    """``noun`` for a count of one, else its plural (``many``, default ``noun + "s"``)."""
    return noun if int(n) == 1 else (many if many is not None else noun + "s")


def counted(n, noun: str, many: str | None = None) -> str:
    """The count and its noun: ``"1 pixel"``, ``"0 pixels"``, ``"1,024 pixels"``.

    Parameters
    ----------
    n : int
        The count (a numpy integer is fine).
    noun : str
        The singular noun; may hold several words ("pixel chunk").
    many : str, optional
        The plural where it is not ``noun + "s"``.
    """
    return f"{int(n):,} {plural(n, noun, many)}"
