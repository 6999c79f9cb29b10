"""One atomic file replacement for every result file of both packages (standard library only, so the
numerical cores of ct_calib_nodes and picms_nodes may use it without pulling in ROS).

``replace_atomically(path, write)`` calls ``write(tmp)`` on a fresh temporary file in path's own
directory (a rename is atomic only within one file system), fsyncs it, renames it over ``path`` and
fsyncs the directory so the rename itself survives a power cut. If ``write`` raises (or anything up
to the rename fails) the temporary file is removed and ``path`` keeps its old content: a partial
result never replaces a good one.

``staged_outputs(out_dir)`` does the same for a set of result files (a command's report, plots and
JSON): they are written into a hidden temporary directory inside ``out_dir`` and moved into place
only when every one was written; if anything fails, ``out_dir`` keeps the previous run's files.
"""
from __future__ import annotations

import contextlib
import os
import pathlib
import shutil
import tempfile


def _fsync_dir(directory: pathlib.Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:            # platforms without directory handles: the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def replace_atomically(path, write, suffix: str = ".tmp") -> pathlib.Path:
    """write(tmp_path) into a temporary file beside ``path``, then rename it over ``path``.

    ``suffix`` ends the temporary name (e.g. ``.tmp.npz`` for writers that add an extension
    themselves). The parent directory is created if needed. Returns ``path`` as a Path.
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix="." + path.name + ".", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)
    return path


def write_text_atomic(path, text: str) -> pathlib.Path:
    """Atomically replace ``path`` by ``text`` (UTF-8)."""
    return replace_atomically(path, lambda tmp: pathlib.Path(tmp).write_text(text, encoding="utf-8"))


def write_bytes_atomic(path, data: bytes) -> pathlib.Path:
    """Atomically replace ``path`` by ``data``."""
    return replace_atomically(path, lambda tmp: pathlib.Path(tmp).write_bytes(data))


@contextlib.contextmanager
def staged_outputs(out_dir):
    """Yield a fresh temporary directory inside ``out_dir`` (created if needed); when the block ends
    without an exception, move each item written there into ``out_dir`` (replacing a file or
    directory of the same name), then remove the temporary directory in every case."""
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=".partial_", dir=out_dir))
    try:
        yield tmp
        for item in sorted(tmp.iterdir()):
            dest = out_dir / item.name
            if dest.is_dir() and not dest.is_symlink():
                shutil.rmtree(dest)
            item.replace(dest)
        _fsync_dir(out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


__all__ = ["replace_atomically", "write_text_atomic", "write_bytes_atomic", "staged_outputs"]
