"""Write-then-rename for output stores and files: an error never leaves half an output or destroys an old one."""
from __future__ import annotations

import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path

from .errors import OutputExistsError

__all__ = ["check_output_path", "staged_output"]


def check_output_path(path, *, overwrite: bool = False) -> None:
    """Refuse to write over an existing, non-empty path unless ``overwrite``."""
    p = Path(path)
    if p.exists() and (p.is_file() or any(p.iterdir())) and not overwrite:
        raise OutputExistsError(f"{path} already exists; pass overwrite=True (--overwrite) to replace it")


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists() or p.is_symlink():
        p.unlink()


@contextmanager
def staged_output(out, *, overwrite: bool = False):
    """Yield a temporary path beside ``out``; on success move it to ``out``.

    ``out`` is checked first (an existing non-empty path needs ``overwrite``).  The
    caller writes a directory store or a file at the yielded path.  If the body raises,
    the temporary is removed and ``out`` is untouched; otherwise an existing ``out``
    is replaced only once the new one is complete.
    """
    out = Path(out).resolve()
    check_output_path(out, overwrite=overwrite)
    tmp = out.parent / f".{out.name}.partial-{uuid.uuid4().hex[:8]}"
    try:
        yield tmp
        if out.exists():
            trash = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(out, trash)
            try:
                os.replace(tmp, out)
            except BaseException:
                os.replace(trash, out)
                raise
            _remove(trash)
        else:
            os.replace(tmp, out)
    finally:
        if tmp.exists() or tmp.is_symlink():
            _remove(tmp)
