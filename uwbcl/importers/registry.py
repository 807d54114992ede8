"""The readers `uwbcl import <name>` knows: one line per radar format."""

from __future__ import annotations

from . import Reader, p440

READERS: dict[str, Reader] = {r.name: r for r in (p440.READER,)}


def get_reader(name: str) -> Reader:
    """The reader registered as ``name``; KeyError naming the available ones otherwise."""
    try:
        return READERS[name]
    except KeyError:
        raise KeyError(f"no reader {name!r}; available: {', '.join(sorted(READERS))}") from None
