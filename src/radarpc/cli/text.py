"""Wording shared by the commands' messages (imports nothing heavy)."""
from __future__ import annotations

__all__ = ["plural"]


def plural(n: int, noun: str, plural_noun: str | None = None) -> str:
    """``n`` followed by ``noun`` in the singular when ``n`` is 1, else in the plural.

    The plural is ``noun + "s"`` unless ``plural_noun`` is given::

        plural(1, "sequence")  -> "1 sequence"
        plural(3, "sequence")  -> "3 sequences"
        plural(0, "CFAR peak") -> "0 CFAR peaks"
    """
    return f"{n} {noun if n == 1 else (plural_noun if plural_noun is not None else noun + 's')}"
