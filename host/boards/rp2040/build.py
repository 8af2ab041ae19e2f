"""Build the emulated board's firmware: MicroPython's rp2 port (BOARD=RPI_PICO) from Debian sources.

Nothing prebuilt is used. The sources come from Debian 13 (trixie, stable), read through a
separate apt state under the output directory so the machine's own apt configuration is left
alone; the machine's Debian ARM toolchain compiles them:

- ``micropython`` source 1.25.0+ds-1 (its orig tarball, unpatched),
- ``pico-sdk-source`` 2.1.1-1 and ``tinyusb-source`` 0.18.0+dfsg-1 (binary packages holding
  sources under ``usr/src/``, unpacked with ``dpkg-deb -x``),
- ``mbedtls`` source 3.6.6-0.1~deb13u1 (its orig tarball).

Every downloaded file is checked against :data:`PINNED` (size and sha256); a missing or
different file stops the build with an error naming it. The tree is laid out as MicroPython's
submodules would be (``lib/pico-sdk``, ``lib/tinyusb``, ``lib/mbedtls``, marker files
``lib/pico-sdk/README.md`` and ``lib/micropython-lib/README.md``), ``mpy-cross`` is built, then
``ports/rp2`` with ``-Dpicotool_FOUND=0`` (no picotool download; the result is ``.bin``/``.elf``,
no ``.uf2``) and the frozen manifest ``host/boards/rp2040/manifest.py``. With
``SOURCE_DATE_EPOCH`` = :data:`SOURCE_DATE_EPOCH` (the package's changelog date),
``PYTHONHASHSEED=0`` (boardgen iterates a set), ``LC_ALL=C``, ``TZ=UTC`` and git kept from
finding the enclosing repository (``makeversionhdr.py`` would otherwise stamp this project's
commit into the version string), two clean builds are byte-identical.

Outputs (repository-relative, under ``build/rp2040/``): ``firmware.bin``, ``firmware.elf``,
``firmware.sha256`` (``sha256sum`` format, both files) and ``inputs.json`` (what the outputs were
built from). The downloads are cached in ``build/rp2040/cache/`` and the build tree is
``build/rp2040/work/`` (kept after a build for its ``firmware.elf.map``/``firmware.dis``).

A run whose outputs are present, match their ``firmware.sha256`` and were built from the same
inputs does nothing. A run whose cache holds all pinned files does not touch the network.

A built ``firmware.bin`` whose sha256 differs from :data:`EXPECTED_FIRMWARE_SHA256` is an
**error**: the outputs are not installed (the stray image is left in the work tree) and the exit
status is 1, since the emulator's tests rely on exactly this image. ``--allow-mismatch`` turns it
into a warning and installs the outputs (for trying other toolchains or manifests).

Run as ``python -m host.boards.rp2040.build`` (``make rp2040``). Only the standard library is used.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tarfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT: Path = Path(__file__).resolve().parents[3]
"""The repository's root (``host/boards/rp2040/build.py`` -> three levels up)."""

DEFAULT_OUT: Path = REPO_ROOT / "build" / "rp2040"
"""Where the outputs, the download cache and the work tree go."""

MANIFEST: Path = Path(__file__).resolve().with_name("manifest.py")
"""The frozen manifest passed to the rp2 port."""

SUITE: str = "trixie"
"""The Debian release the sources come from."""

MIRROR: str = "http://deb.debian.org/debian"
"""The Debian archive (reached through the machine's normal network configuration)."""

KEYRING: Path = Path("/usr/share/keyrings/debian-archive-keyring.gpg")
"""The archive keyring the separate apt state trusts (package ``debian-archive-keyring``)."""

SOURCE_DATE_EPOCH: int = 1746366018
"""Timestamp for the build (the date of micropython 1.25.0+ds-1's changelog entry)."""

EXPECTED_FIRMWARE_SHA256: str = "3ec80c9d9a79893b0b003f096d193d93f28d9997f47fb1c0e1824c78b75a9db2"
"""sha256 of the reproducible ``firmware.bin`` (333,396 bytes) built with :data:`MANIFEST` and
:data:`LD_PATCH` (331,804 bytes, ``68f0d5fe...``, without the patch)."""

EXPECTED_FIRMWARE_SIZE: int = 333_396
"""Size in bytes of the expected ``firmware.bin``."""

MICROPYTHON_DIR: str = "micropython-1.25.0"
"""Top directory of the micropython orig tarball."""

BOARD: str = "RPI_PICO"
"""The rp2 port's board."""


@dataclass(frozen=True)
class Pin:
    """One pinned Debian file.

    Parameters
    ----------
    name : str
        File name as the archive serves it.
    size : int
        Size in bytes.
    sha256 : str
        Hex sha256 of the file.
    """

    name: str
    size: int
    sha256: str


@dataclass(frozen=True)
class Package:
    """One pinned Debian package and the files apt fetches for it.

    Parameters
    ----------
    name : str
        Source package name (``kind == "source"``) or binary package name (``kind == "binary"``).
    version : str
        Exact Debian version.
    kind : str
        ``"source"`` (fetched with ``apt-get source --download-only``) or ``"binary"``
        (fetched with ``apt-get download``).
    files : tuple of Pin
        Every file apt fetches for it, pinned.
    """

    name: str
    version: str
    kind: str
    files: tuple[Pin, ...]


PINNED: tuple[Package, ...] = (
    Package("micropython", "1.25.0+ds-1", "source", (
        Pin("micropython_1.25.0+ds.orig.tar.xz", 5_983_992,
            "7b25be99a502f070b2de81dafc08da7051d992325d6e67daa9045a918fffdbea"),
        Pin("micropython_1.25.0+ds-1.debian.tar.xz", 15_664,
            "87cd89f7900c86b963885dabe25acf3e5348815993f1500278ad8f6464465af4"),
        Pin("micropython_1.25.0+ds-1.dsc", 2_116,
            "8c7c406be88a6f3bc19e694eb0bbc5841112243fdf2b5a296e000d8fdc5f3c34"),
    )),
    Package("mbedtls", "3.6.6-0.1~deb13u1", "source", (
        Pin("mbedtls_3.6.6.orig.tar.bz2", 5_508_045,
            "8fb65fae8dcae5840f793c0a334860a411f884cc537ea290ce1c52bb64ca007a"),
        Pin("mbedtls_3.6.6-0.1~deb13u1.debian.tar.xz", 19_084,
            "210466c522eeebc85cf2f76bd5aef935b4ebac465559cc0a84f9e73a8ed6601c"),
        Pin("mbedtls_3.6.6-0.1~deb13u1.dsc", 2_490,
            "eb9ed1adbbddcb0d00276fac6fcee0056c64ce01481c2522a16dca75792eb5eb"),
    )),
    Package("pico-sdk-source", "2.1.1-1", "binary", (
        Pin("pico-sdk-source_2.1.1-1_all.deb", 2_383_548,
            "507a3ca37636641bc90239d7c04dc9dc28c5008087a8162102ea94d2273153d3"),
    )),
    Package("tinyusb-source", "0.18.0+dfsg-1", "binary", (
        Pin("tinyusb-source_0.18.0+dfsg-1_all.deb", 1_320_704,
            "01ce2c645df68f14a8a7dcfc8fb355713152543757955820479a87949a61154e"),
    )),
)
"""The Debian packages the firmware is built from, with every file's size and sha256."""

TOOLS: dict[str, str] = {
    "arm-none-eabi-gcc": "gcc-arm-none-eabi",
    "arm-none-eabi-g++": "gcc-arm-none-eabi",
    "cmake": "cmake",
    "make": "make",
    "gcc": "gcc",
    "dpkg-deb": "dpkg",
    "apt-get": "apt",
}
"""Commands the build runs -> the Debian package that provides each."""

TOOLCHAIN_FILES: dict[str, str] = {
    "libc.a": "libnewlib-arm-none-eabi",
    "libstdc++.a": "libstdc++-arm-none-eabi-newlib",
}
"""Libraries ``arm-none-eabi-gcc`` must find -> the Debian package that provides each."""

APT_PACKAGES: str = ("gcc-arm-none-eabi libnewlib-arm-none-eabi libstdc++-arm-none-eabi-newlib "
                     "cmake make gcc libc6-dev debian-archive-keyring")
"""What ``make rp2040`` installs (the Makefile's ``APT_PACKAGES``), for the error messages."""


class BuildError(RuntimeError):
    """The firmware cannot be built; the message says why and what to do."""


def sha256_of(path: Path) -> str:
    """Hex sha256 of a file.

    Parameters
    ----------
    path : Path
        The file.

    Returns
    -------
    str
        64 lowercase hex digits.
    """
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def log(msg: str) -> None:
    """Print a progress line (stderr, flushed).

    Parameters
    ----------
    msg : str
        The line.
    """
    print(f"rp2040: {msg}", file=sys.stderr, flush=True)


def check_toolchain() -> None:
    """Stop unless every command and library the build needs is installed.

    Raises
    ------
    BuildError
        Naming each missing command or library and the Debian package that provides it.
    """
    missing: dict[str, str] = {}
    for tool, pkg in TOOLS.items():
        if shutil.which(tool) is None:
            missing[tool] = pkg
    if "arm-none-eabi-gcc" not in missing:
        for lib, pkg in TOOLCHAIN_FILES.items():
            out = subprocess.run(["arm-none-eabi-gcc", f"-print-file-name={lib}"],
                                 capture_output=True, text=True, check=False).stdout.strip()
            if not os.path.isabs(out) or not os.path.exists(out):
                missing[lib] = pkg
    if not KEYRING.exists():
        missing[str(KEYRING)] = "debian-archive-keyring"
    if missing:
        lines = ", ".join(f"{what} (package {pkg})" for what, pkg in missing.items())
        pkgs = " ".join(sorted(set(missing.values())))
        raise BuildError(f"missing: {lines}. Install with `apt-get install -y --no-install-recommends "
                         f"{pkgs}` (or `make rp2040`, which installs {APT_PACKAGES}).")


def native_arch() -> str:
    """The machine's Debian architecture (``dpkg --print-architecture``).

    Returns
    -------
    str
        For instance ``"amd64"``.
    """
    return subprocess.run(["dpkg", "--print-architecture"], capture_output=True, text=True,
                          check=True).stdout.strip()


def apt_options(state: Path) -> list[str]:
    """apt-get options for a separate apt state reading only trixie main.

    Writes the list file under ``state`` and creates the directories apt needs. The machine's
    ``/etc/apt`` sources, lists and archive cache are not read or written.

    Parameters
    ----------
    state : Path
        Directory of the separate apt state.

    Returns
    -------
    list of str
        ``-o`` options to pass to ``apt-get``.
    """
    etc = state / "etc"
    parts = etc / "sources.list.d"
    lists = state / "lists"
    cache = state / "cache"
    for d in (parts, lists / "partial", cache / "archives" / "partial"):
        d.mkdir(parents=True, exist_ok=True)
    arch = native_arch()
    opts = f"[arch={arch} signed-by={KEYRING}]"
    (etc / "sources.list").write_text(
        f"deb {opts} {MIRROR} {SUITE} main\n"
        f"deb-src [signed-by={KEYRING}] {MIRROR} {SUITE} main\n")
    o = [
        f"Dir::Etc::sourcelist={etc / 'sources.list'}",
        f"Dir::Etc::sourceparts={parts}",
        f"Dir::State::Lists={lists}",
        f"Dir::Cache={cache}",
        "Acquire::Languages=none",
        "APT::Get::List-Cleanup=false",
    ]
    if os.geteuid() == 0:
        o.append("APT::Sandbox::User=root")  # _apt may not be able to write into the cache
    return [x for opt in o for x in ("-o", opt)]


def run(cmd: list[str], cwd: Path | None = None, env: dict[str, str] | None = None,
        logfile: Path | None = None) -> None:
    """Run a command; on failure raise with the command and the tail of its output.

    Parameters
    ----------
    cmd : list of str
        The command.
    cwd : Path, optional
        Working directory.
    env : dict, optional
        Environment (default: inherited).
    logfile : Path, optional
        Where the output goes (default: captured and shown only on failure).

    Raises
    ------
    BuildError
        If the command exits non-zero.
    """
    if logfile is not None:
        with logfile.open("w") as f:
            rc = subprocess.run(cmd, cwd=cwd, env=env, stdout=f, stderr=subprocess.STDOUT,
                                check=False).returncode
        tail = "\n".join(logfile.read_text(errors="replace").splitlines()[-30:])
    else:
        p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, check=False)
        rc, tail = p.returncode, "\n".join((p.stdout + p.stderr).splitlines()[-30:])
    if rc != 0:
        where = f" (full log: {logfile})" if logfile else ""
        raise BuildError(f"`{' '.join(cmd)}` failed with status {rc}{where}:\n{tail}")


def verify(cache: Path, pin: Pin) -> str | None:
    """Check one cached file against its pin.

    Parameters
    ----------
    cache : Path
        Download directory.
    pin : Pin
        The pinned file.

    Returns
    -------
    str or None
        None if the file is there with the pinned size and sha256, else what is wrong.
    """
    path = cache / pin.name
    if not path.is_file():
        return "missing"
    size = path.stat().st_size
    if size != pin.size:
        return f"size {size}, pinned {pin.size}"
    digest = sha256_of(path)
    if digest != pin.sha256:
        return f"sha256 {digest}, pinned {pin.sha256}"
    return None


def fetch(cache: Path, state: Path) -> int:
    """Download the pinned packages that are not in the cache yet, and verify all of them.

    Parameters
    ----------
    cache : Path
        Download directory (files land here under their archive names).
    state : Path
        Directory of the separate apt state.

    Returns
    -------
    int
        Bytes downloaded (0 when everything was cached).

    Raises
    ------
    BuildError
        If apt cannot find a pinned package version, or a file is missing or differs from its pin
        (the message names the package and the file).
    """
    cache.mkdir(parents=True, exist_ok=True)
    todo = [pkg for pkg in PINNED if any(verify(cache, p) for p in pkg.files)]
    if not todo:
        return 0
    for pkg in todo:  # a partial or stale file would make apt skip or resume it: start clean
        for p in pkg.files:
            (cache / p.name).unlink(missing_ok=True)
    opts = apt_options(state)
    log(f"reading the {SUITE} package index from {MIRROR} (separate apt state {state})")
    run(["apt-get", *opts, "update"])
    for pkg in todo:
        spec = f"{pkg.name}={pkg.version}"
        log(f"downloading {spec} ({pkg.kind})")
        if pkg.kind == "source":
            cmd = ["apt-get", *opts, "source", "--download-only", spec]
        else:
            cmd = ["apt-get", *opts, "download", spec]
        try:
            run(cmd, cwd=cache)
        except BuildError as e:
            raise BuildError(f"pinned package {spec} could not be downloaded from {SUITE} "
                             f"(is it still in the archive?): {e}") from None
    bad = [(pkg, p, why) for pkg in todo for p in pkg.files if (why := verify(cache, p))]
    if bad:
        raise BuildError("downloaded files differ from their pins: " + "; ".join(
            f"{pkg.name} {pkg.version}: {p.name}: {why}" for pkg, p, why in bad))
    return sum(p.size for pkg in todo for p in pkg.files)


def _extract_tar(archive: Path, dest: Path, strip: int = 0) -> None:
    """Unpack a tarball (xz or bz2), optionally dropping leading path components.

    Parameters
    ----------
    archive : Path
        The tarball.
    dest : Path
        Directory to unpack into (created).
    strip : int
        Leading path components to drop, as ``tar --strip-components``.
    """
    dest.mkdir(parents=True, exist_ok=True)
    with tarfile.open(archive) as tf:
        members = []
        for m in tf.getmembers():
            parts = Path(m.name).parts[strip:]
            if not parts:
                continue
            m.name = str(Path(*parts))
            members.append(m)
        kwargs = {"filter": "tar"} if hasattr(tarfile, "tar_filter") else {}
        tf.extractall(dest, members=members, **kwargs)


def lay_out(cache: Path, work: Path) -> Path:
    """Unpack the sources into a fresh work tree, as MicroPython's submodules would be.

    Parameters
    ----------
    cache : Path
        Directory holding the verified downloads.
    work : Path
        Work directory (emptied first).

    Returns
    -------
    Path
        The MicroPython source tree.
    """
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    _extract_tar(cache / "micropython_1.25.0+ds.orig.tar.xz", work)
    mpy = work / MICROPYTHON_DIR
    debs = work / "debs"
    for deb in ("pico-sdk-source_2.1.1-1_all.deb", "tinyusb-source_0.18.0+dfsg-1_all.deb"):
        run(["dpkg-deb", "-x", str(cache / deb), str(debs)])
    lib = mpy / "lib"
    for name in ("pico-sdk", "tinyusb"):
        target = lib / name
        if target.exists():
            target.rmdir()  # the empty submodule directory
        # symlinks=True keeps pico-sdk's lib/tinyusb -> ../../tinyusb, which lands on lib/tinyusb
        shutil.copytree(debs / "usr" / "src" / name, target, symlinks=True)
    shutil.rmtree(debs)
    _extract_tar(cache / "mbedtls_3.6.6.orig.tar.bz2", lib / "mbedtls", strip=1)
    # ports/rp2/Makefile and py/mkrules.mk test for these to tell a checked-out submodule
    (lib / "pico-sdk" / "README.md").touch()
    (lib / "micropython-lib").mkdir(exist_ok=True)
    (lib / "micropython-lib" / "README.md").touch()
    return mpy


LD_FILE: str = "ports/rp2/memmap_mp_rp2040.ld"
"""The rp2 port's linker script (relative to the MicroPython tree)."""

LD_PATCH: tuple[tuple[str, str], ...] = (
    ("*gc.c.obj *vm.c.obj *parse.c.obj", "*gc.c.o *vm.c.o *parse.c.o"),
)
"""The one source edit of the board image: the linker script keeps ``py/vm.c``, ``py/gc.c`` and
``py/parse.c`` in SRAM with patterns pico-sdk 1.x object names matched (``*vm.c.obj``); pico-sdk 2.x
names them ``*.c.o``, so unpatched MicroPython 1.25 runs its VM, GC and parser from flash through
the XIP cache (upstream fixed the patterns in 2026, MicroPython PR #19370)."""


def patch_linker_script(mpy: Path) -> None:
    """Apply :data:`LD_PATCH` to the MicroPython tree ``mpy`` (the hot code back in SRAM).

    Raises
    ------
    BuildError
        The linker script does not hold a pattern exactly once (another source).
    """
    ld = mpy / LD_FILE
    text = ld.read_text()
    for old, new in LD_PATCH:
        if text.count(old) != 1:
            raise BuildError(f"{ld}: pattern {old!r} not found once; the SRAM patch does not apply to this source")
        text = text.replace(old, new)
    ld.write_text(text)


def build_env(work: Path) -> dict[str, str]:
    """The environment for a reproducible build.

    Parameters
    ----------
    work : Path
        Work directory; git is not allowed to look above it.

    Returns
    -------
    dict
        The inherited environment with the reproducibility variables set and the variables
        that could change the build (compiler flags, make's job server, Pico SDK paths) removed.
    """
    env = {k: v for k, v in os.environ.items()
           if k not in {"CFLAGS", "CXXFLAGS", "CPPFLAGS", "LDFLAGS", "MAKEFLAGS", "MFLAGS",
                        "MAKELEVEL", "GIT_DIR", "GIT_WORK_TREE", "CC", "CXX"}
           and not k.startswith(("PICO_", "MICROPY_"))}
    env.update(SOURCE_DATE_EPOCH=str(SOURCE_DATE_EPOCH), PYTHONHASHSEED="0", LC_ALL="C", TZ="UTC",
               GIT_CEILING_DIRECTORIES=str(work))
    return env


def compile_firmware(mpy: Path, work: Path, jobs: int) -> Path:
    """Build ``mpy-cross`` and then the rp2 port.

    Parameters
    ----------
    mpy : Path
        The laid-out MicroPython tree.
    work : Path
        Work directory (for the logs and git's ceiling).
    jobs : int
        Parallel jobs for make.

    Returns
    -------
    Path
        The port's build directory (holding ``firmware.bin`` and ``firmware.elf``).
    """
    env = build_env(work)
    log(f"building mpy-cross (log {work / 'mpy-cross.log'})")
    run(["make", "-C", "mpy-cross", f"-j{jobs}"], cwd=mpy, env=env, logfile=work / "mpy-cross.log")
    log(f"building ports/rp2 BOARD={BOARD} (log {work / 'rp2.log'})")
    cmake_args = f"-Dpicotool_FOUND=0 -DMICROPY_FROZEN_MANIFEST={MANIFEST}"
    run(["make", "-C", "ports/rp2", f"BOARD={BOARD}", f"-j{jobs}", f"CMAKE_ARGS={cmake_args}"],
        cwd=mpy, env=env, logfile=work / "rp2.log")
    return mpy / "ports" / "rp2" / f"build-{BOARD}"


def inputs_record() -> dict[str, object]:
    """What the outputs depend on, to tell whether a previous build is still current.

    Returns
    -------
    dict
        Pins, manifest digest, board, timestamp and expected image digest.
    """
    return {
        "packages": [{"name": p.name, "version": p.version, "kind": p.kind,
                      "files": {f.name: f.sha256 for f in p.files}} for p in PINNED],
        "manifest_sha256": sha256_of(MANIFEST),
        "board": BOARD,
        "cmake_args": ["-Dpicotool_FOUND=0", "-DMICROPY_FROZEN_MANIFEST=<manifest>"],
        "source_date_epoch": SOURCE_DATE_EPOCH,
        "ld_patch": [LD_FILE, *(list(p) for p in LD_PATCH)],
        "expected_firmware_sha256": EXPECTED_FIRMWARE_SHA256,
    }


def up_to_date(out: Path) -> bool:
    """Whether the outputs in ``out`` are present, intact and built from the current inputs.

    Parameters
    ----------
    out : Path
        Output directory.

    Returns
    -------
    bool
        True if there is nothing to do.
    """
    files = [out / n for n in ("firmware.bin", "firmware.elf", "firmware.sha256", "inputs.json")]
    if not all(f.is_file() for f in files):
        return False
    try:
        if json.loads((out / "inputs.json").read_text()) != inputs_record():
            return False
    except ValueError:
        return False
    recorded = dict(reversed(line.split(None, 1)) for line in
                    (out / "firmware.sha256").read_text().splitlines() if line.strip())
    return all(recorded.get(n) == sha256_of(out / n) for n in ("firmware.bin", "firmware.elf"))


def build(out: Path = DEFAULT_OUT, cache: Path | None = None, jobs: int | None = None,
          force: bool = False, allow_mismatch: bool = False) -> Path:
    """Build the firmware unless it is already built from the same inputs.

    Parameters
    ----------
    out : Path
        Output directory (default ``build/rp2040``).
    cache : Path, optional
        Download cache (default ``<out>/cache``).
    jobs : int, optional
        Parallel jobs (default: the number of CPUs).
    force : bool
        Rebuild even if the outputs are current (the download cache is still used).
    allow_mismatch : bool
        Install an image whose sha256 differs from :data:`EXPECTED_FIRMWARE_SHA256` with a
        warning instead of stopping.

    Returns
    -------
    Path
        The installed ``firmware.bin``.

    Raises
    ------
    BuildError
        Missing tools, an unavailable or altered package, a failed compile, or (without
        ``allow_mismatch``) an image other than the pinned one.
    """
    out = out.resolve()
    if not force and up_to_date(out):
        log(f"up to date: {out / 'firmware.bin'} ({EXPECTED_FIRMWARE_SHA256[:16]}...)")
        return out / "firmware.bin"
    check_toolchain()
    cache = (cache or out / "cache").resolve()
    work = out / "work"
    t0 = time.monotonic()
    downloaded = fetch(cache, out / "apt")
    t1 = time.monotonic()
    log(f"sources verified ({downloaded:,} bytes of packages downloaded, {t1 - t0:.1f} s)")
    for stale in ("firmware.bin", "firmware.elf", "firmware.sha256", "inputs.json"):
        (out / stale).unlink(missing_ok=True)
    mpy = lay_out(cache, work)
    patch_linker_script(mpy)
    built = compile_firmware(mpy, work, jobs or os.cpu_count() or 1)
    t2 = time.monotonic()
    bin_path, elf_path = built / "firmware.bin", built / "firmware.elf"
    digest, size = sha256_of(bin_path), bin_path.stat().st_size
    log(f"built firmware.bin: {size:,} bytes, sha256 {digest} (compile {t2 - t1:.0f} s)")
    if digest != EXPECTED_FIRMWARE_SHA256:
        msg = (f"firmware.bin sha256 {digest} ({size:,} bytes) differs from the pinned "
               f"{EXPECTED_FIRMWARE_SHA256} ({EXPECTED_FIRMWARE_SIZE:,} bytes)")
        if not allow_mismatch:
            raise BuildError(f"{msg}; not installed (image left at {bin_path}; "
                             "--allow-mismatch installs it)")
        log(f"WARNING: {msg}; installed anyway (--allow-mismatch)")
    shutil.copyfile(elf_path, out / "firmware.elf")
    shutil.copyfile(bin_path, out / "firmware.bin")
    (out / "firmware.sha256").write_text(
        f"{digest}  firmware.bin\n{sha256_of(out / 'firmware.elf')}  firmware.elf\n")
    (out / "inputs.json").write_text(json.dumps(inputs_record(), indent=1) + "\n")
    log(f"installed {out / 'firmware.bin'} and firmware.elf (total {time.monotonic() - t0:.0f} s)")
    return out / "firmware.bin"


def main(argv: list[str] | None = None) -> int:
    """Command line: build the emulated board's firmware.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status: 0 built or up to date, 1 on any error.
    """
    ap = argparse.ArgumentParser(prog="python -m host.boards.rp2040.build",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output directory (%(default)s)")
    ap.add_argument("--cache", type=Path, default=None, help="download cache (<out>/cache)")
    ap.add_argument("-j", "--jobs", type=int, default=None, help="parallel jobs (CPU count)")
    ap.add_argument("--force", action="store_true", help="rebuild even if up to date")
    ap.add_argument("--allow-mismatch", action="store_true",
                    help="install an image whose sha256 differs from the pinned one (warning)")
    a = ap.parse_args(argv)
    try:
        build(a.out, a.cache, a.jobs, a.force, a.allow_mismatch)
    except BuildError as e:
        print(f"rp2040: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
