"""Output files are never clobbered by accident: one check used by every command that writes.

``indoor-loc run``, ``recorder``/``indoor-loc record``, ``indoor-loc import`` and ``radiomap build``
refuse (ConfigError -> exit 2) to write a file that exists unless the user passes ``--overwrite``,
and always refuse to write where an input is being read (``run IN.mcap --out IN.mcap``).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

from indoor_loc.errors import ConfigError


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_output(path: str | os.PathLike, *, inputs: Iterable[str | os.PathLike] = (), overwrite: bool = False,
                 what: str = "output") -> Path:
    """Return ``Path(path)`` if writing it is safe, else raise ConfigError saying why.

    Args:
        path: the file about to be written.
        inputs: files read by the same command; writing one of them is refused even with
            ``overwrite`` (the run would destroy its own input).
        overwrite: the user asked to replace an existing file.
        what: how the message names the file (``"--out"``, ``"-o"``...).
    """
    out = Path(path)
    for src in inputs:
        src = Path(src)
        if _same(out, src) or out.resolve() == src.resolve():
            raise ConfigError(f"{what} {out} is also an input of this command; refusing to write where an input is "
                              "being read (choose another output file)")
    if out.is_dir():
        raise ConfigError(f"{what} {out} is a directory; expected a file name")
    if out.exists() and not overwrite:
        raise ConfigError(f"{what} {out} exists; refusing to overwrite it (pass --overwrite to replace it)")
    return out


def check_outputs(paths: Iterable[str | os.PathLike], *, overwrite: bool = False, what: str = "output") -> None:
    """:func:`check_output` for several files at once, naming all existing ones in one message."""
    existing = [str(p) for p in paths if Path(p).exists()]
    if existing and not overwrite:
        shown = ", ".join(existing[:5]) + (f" and {len(existing) - 5} more" if len(existing) > 5 else "")
        raise ConfigError(f"{what}: {shown} exist(s); refusing to overwrite (pass --overwrite to replace)")
