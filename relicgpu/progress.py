"""Progress bars on stderr, shared by the stages and the command line."""
from __future__ import annotations

import sys

def progress_bar(total: int, desc: str, progress: bool = True, unit: str = "it"):
    """A tqdm bar on stderr, shown only when `progress` (no ``--quiet``) and stderr is a
    terminal, as the command line's other bars; it vanishes when done (``leave=False``).
    Units "faces" and "B" (bytes) are shown scaled (1.35M faces, 95.2MB)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False, dynamic_ncols=True,
                disable=not (progress and sys.stderr.isatty()), unit_scale=unit in ("faces", "B"))
