"""LittleFS image of a directory, as MicroPython's rp2 port (RPI_PICO) mounts it.

RPI_PICO keeps its filesystem in flash at offset ``0xA0000``: LittleFS v2, 352 blocks of
4096 bytes, read/prog size 256, lookahead 32 bytes.  :func:`build_image` lays a directory (a
firmware bundle: ``main.py`` plus ``firmware/*.mpy``) into such an image with PyPI
``littlefs-python``, for the emulated board (:mod:`host.boards.rp2040.board`) to place in flash.

The image is written in on-disk format 2.0 (``disk_version=0x00020000``): every littlefs 2.x
reads it, whichever littlefs release the MicroPython image was built with (littlefs-python
0.19 bundles littlefs 2.11, which would otherwise write 2.1).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

__all__ = [
    "FS_OFFSET",
    "BLOCK_SIZE",
    "BLOCK_COUNT",
    "READ_SIZE",
    "PROG_SIZE",
    "LOOKAHEAD_SIZE",
    "DISK_VERSION",
    "build_image",
    "read_image",
]

FS_OFFSET = 0xA0000
BLOCK_SIZE = 4096
BLOCK_COUNT = 352
READ_SIZE = 256
PROG_SIZE = 256
LOOKAHEAD_SIZE = 32
DISK_VERSION = 0x00020000


def _new_fs(mount: bool = True):  # type: ignore[no-untyped-def]
    from littlefs import LittleFS

    return LittleFS(
        block_size=BLOCK_SIZE,
        block_count=BLOCK_COUNT,
        read_size=READ_SIZE,
        prog_size=PROG_SIZE,
        lookahead_size=LOOKAHEAD_SIZE,
        disk_version=DISK_VERSION,
        mount=mount,
    )


def build_image(src: str | Path | None = None, *, extra: Mapping[str, bytes] | None = None) -> bytes:
    """Build the filesystem image of a directory.

    Parameters
    ----------
    src : str or Path or None
        Directory whose tree becomes the filesystem root (hidden entries, ``__pycache__`` and
        ``.pyc`` files are left out).  ``None``: start from an empty filesystem.
    extra : mapping of str to bytes, optional
        Files to add or replace, by path relative to the root (``"main.py"``,
        ``"lib/x.py"``); parent directories are created.

    Returns
    -------
    bytes
        The image: ``BLOCK_SIZE * BLOCK_COUNT`` bytes (1,441,792), to be written at flash offset
        :data:`FS_OFFSET`.

    Raises
    ------
    FileNotFoundError
        If ``src`` is not a directory.
    littlefs.LittleFSError
        If the files do not fit.
    """
    files: dict[str, bytes] = {}
    if src is not None:
        root = Path(src)
        if not root.is_dir():
            raise FileNotFoundError(f"not a directory: {root}")
        for path in sorted(root.rglob("*")):
            rel = path.relative_to(root)
            if any(part.startswith(".") or part == "__pycache__" for part in rel.parts):
                continue
            if path.is_file() and path.suffix != ".pyc":
                files[rel.as_posix()] = path.read_bytes()
    for name, data in (extra or {}).items():
        files[name.strip("/")] = bytes(data)

    fs = _new_fs()
    made: set[str] = set()
    for name in sorted(files):
        parts = name.split("/")
        for i in range(1, len(parts)):
            d = "/".join(parts[:i])
            if d not in made:
                fs.makedirs(d, exist_ok=True)
                made.add(d)
        with fs.open(name, "wb") as fh:
            fh.write(files[name])
    fs.unmount()
    return bytes(fs.context.buffer)


def read_image(image: bytes) -> dict[str, bytes]:
    """Read every file of an image back (for checks and for inspecting a board's flash).

    Parameters
    ----------
    image : bytes
        An image as :func:`build_image` returns it (or the same region of a flash dump).

    Returns
    -------
    dict of str to bytes
        File contents by path relative to the root.
    """
    from littlefs import LittleFS
    from littlefs.context import UserContext

    fs = LittleFS(
        context=UserContext(buffer=bytearray(image[: BLOCK_SIZE * BLOCK_COUNT])),
        block_size=BLOCK_SIZE,
        block_count=BLOCK_COUNT,
        read_size=READ_SIZE,
        prog_size=PROG_SIZE,
        lookahead_size=LOOKAHEAD_SIZE,
        mount=True,
    )
    out: dict[str, bytes] = {}
    for top, _dirs, names in fs.walk("/"):
        for n in names:
            p = f"{top.rstrip('/')}/{n}"
            with fs.open(p, "rb") as fh:
                out[p.lstrip("/")] = fh.read()
    return out
