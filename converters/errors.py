"""The one error type of the converter: every bad input ends here, with the key, file and shapes named."""

from __future__ import annotations


class ConversionError(ValueError):
    """A source checkpoint (or the destination) cannot be converted. The message names the culprit."""


def listing(items, limit: int = 8) -> str:
    """'a', 'b', ... and N more: long key lists stay readable in one error line."""
    items = sorted(items)
    shown = ", ".join(repr(x) for x in items[:limit])
    return shown + (f" ... and {len(items) - limit} more" if len(items) > limit else "")
