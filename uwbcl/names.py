"""File-name components taken from file content (rig ids) or from a device (IDENTITY.RIG_ID): data, never
paths.

The one place that turns such text into a name: archives written by `uwbcl acquire`, `uwbcl import` and
`uwbcl simulate` (archive.default_relative_path) and the plots of `uwbcl process` all use it, so no id can
climb out of the directory it names a file in.
"""

from __future__ import annotations

import hashlib

SAFE_NAME_CHARACTERS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._-")
MAX_NAME_LENGTH = 64


def safe_name(text: str) -> str:
    """A file-name component derived from file content (a rig id): the characters docs/archive-format.md calls
    safe, other characters as '_', no leading dot, at most MAX_NAME_LENGTH characters. A name that had to be
    changed gets a hash of the original, so two ids never share a file. Never a path: no '/', never '..'."""
    clean = "".join(c if c in SAFE_NAME_CHARACTERS else "_" for c in text).lstrip(".") or "_"
    if clean == text and len(text) <= MAX_NAME_LENGTH:
        return text
    digest = hashlib.sha256(text.encode("utf-8", "surrogateescape")).hexdigest()[:8]
    return f"{clean[:MAX_NAME_LENGTH - 9]}-{digest}"
