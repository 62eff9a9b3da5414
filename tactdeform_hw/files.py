"""Writing the files a session depends on (participant and calibration profiles) so that a crash never
leaves half of one where a valid one used to be."""

from __future__ import annotations

import os
from pathlib import Path


def write_text_atomically(path: Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to a hidden file beside ``path``, then move it over ``path`` in one step: a
    reader sees the old file or the new one, never a part.  Returns ``path``."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path
