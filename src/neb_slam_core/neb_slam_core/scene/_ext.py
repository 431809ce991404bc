"""Build and load the C++/OpenMP extension (``csrc/hash_grid.cpp``: the hash-grid, one-blob and decoder
kernels) on first use.

The extension is compiled with ``torch.utils.cpp_extension.load`` (ninja) the first time a process asks
for it and cached on disk. The cache folder is named by a hash of everything that makes the binary: the
source, the compiler flags, the torch and Python versions and the CPU architecture and instruction set,
so a cache shared between machines (or a home folder moved to another CPU) never loads a binary built for
something else; it rebuilds instead.

Cache location, first that is set: ``$NEB_SLAM_EXT_DIR``, ``$TORCH_EXTENSIONS_DIR``,
``$XDG_CACHE_HOME/neb_slam/torch_extensions``, ``~/.cache/neb_slam/torch_extensions``.

A failed build (no compiler, no ninja, an unsupported platform) is remembered for the rest of the process:
:func:`load_hash_grid_ext` raises :class:`ExtensionUnavailable` with the reason, once built or not.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import platform
import sys
import threading
from pathlib import Path
from types import ModuleType

import torch

log = logging.getLogger(__name__)

CSRC = Path(__file__).resolve().parent / "csrc"
SOURCE = CSRC / "hash_grid.cpp"  # the torch binding; it includes the kernels, csrc/hash_grid_kernels.h

_module: ModuleType | None = None
_failure: str | None = None
_lock = threading.Lock()  # one build per process even when several threads ask at once


class ExtensionUnavailable(RuntimeError):
    """The fast CPU path could not be built or loaded; ``reason`` says why."""

    def __init__(self, reason: str):
        self.reason = reason
        super().__init__(f"hash-grid C++ extension unavailable: {reason}")


def compile_flags() -> list[str]:
    """Portable optimisation flags, plus AVX2/FMA only when torch reports this CPU supports them.

    No ``-march=native``: the cache folder's hash includes these flags and the CPU capability, so a binary
    is never reused on a CPU that lacks what it was built for.
    """
    # -fno-trapping-math lets the compiler turn the clamps and selects of the kernels into branch-free
    # vector code (5x on the cell computation); the kernels never rely on floating-point exceptions.
    flags = ["-O3", "-fopenmp", "-fno-trapping-math"]
    if platform.machine().lower() in ("x86_64", "amd64"):
        capability = torch.backends.cpu.get_cpu_capability()  # "DEFAULT", "AVX2", "AVX512", ...
        if capability in ("AVX2", "AVX512"):
            flags += ["-mavx2", "-mfma"]
    return flags


def cache_root() -> Path:
    for var in ("NEB_SLAM_EXT_DIR", "TORCH_EXTENSIONS_DIR"):
        value = os.environ.get(var)
        if value:
            return Path(value).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "neb_slam" / "torch_extensions"


def build_key(flags: list[str]) -> str:
    """Hash of the sources, flags, torch/Python versions and CPU: names the build (and its cache folder)."""
    h = hashlib.sha256()
    for path in sorted(CSRC.glob("*")):
        if path.suffix in (".cpp", ".h"):
            h.update(path.name.encode() + b"\0" + path.read_bytes())
    for part in (
        " ".join(flags),
        torch.__version__,
        f"{sys.version_info.major}.{sys.version_info.minor}",
        platform.system(),
        platform.machine(),
        torch.backends.cpu.get_cpu_capability(),
    ):
        h.update(b"\0" + part.encode())
    return h.hexdigest()[:16]


def load_hash_grid_ext() -> ModuleType:
    """The compiled extension (built on the first call of the process, from the disk cache after that).

    Raises:
        ExtensionUnavailable: the build or the import failed (the reason is kept for the process).
    """
    global _module, _failure
    if _module is not None:
        return _module
    with _lock:
        if _module is None and _failure is None:
            try:
                _module = _build()
            except Exception as exc:  # compiler error, no ninja, import error: all mean "use the reference"
                log.debug("hash-grid extension build failed", exc_info=True)
                first_line = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
                _failure = f"{type(exc).__name__}: {first_line}"
        if _module is None:
            raise ExtensionUnavailable(_failure or "unknown")
        return _module


def prepare(backend: str) -> None:
    """Build (first use) or load the extension now unless ``backend`` is ``"reference"``: ``neb-slam run``
    does this before its first frame, so that a one-time compile is not timed as that frame's work. A
    failure is only remembered here; the modules report it where they would use the extension
    (``"auto"`` falls back, ``"fast"`` raises)."""
    if backend != "reference":
        unavailable_reason()


def unavailable_reason() -> str | None:
    """Why the extension cannot be used in this process (builds it if needed), or ``None`` if it can."""
    try:
        load_hash_grid_ext()
    except ExtensionUnavailable as exc:
        return exc.reason
    return None


def use_fast_path(backend: str, eligible: bool, owner: str, needs: str) -> bool:
    """The backend rule of the modules with a C++ path (one-blob, decoders): ``"reference"`` never,
    ``"fast"`` always (an error when the inputs are not ``eligible``, described by ``needs``, or the
    extension is unavailable), ``"auto"`` when eligible and the extension loads."""
    if backend == "reference":
        return False
    if backend == "fast":
        if not eligible:
            raise ValueError(f"{owner} backend 'fast' needs {needs}")
        try:
            load_hash_grid_ext()
        except ExtensionUnavailable as exc:
            raise RuntimeError(f"{owner} backend 'fast' requested but unavailable: {exc.reason}") from exc
        return True
    return eligible and unavailable_reason() is None


def _build() -> ModuleType:
    from torch.utils import cpp_extension

    if not SOURCE.is_file():
        raise FileNotFoundError(f"extension source missing: {SOURCE.name} (package data not installed?)")
    flags = compile_flags()
    name = f"neb_hash_grid_{build_key(flags)}"
    build_dir = cache_root() / name
    build_dir.mkdir(parents=True, exist_ok=True)
    already_built = any(build_dir.glob(f"{name}*.so"))
    if not already_built:
        log.info("compiling the hash-grid CPU extension (first use only), cache: %s", build_dir)
    with _build_guard(build_dir):
        return cpp_extension.load(
            name=name,
            sources=[str(SOURCE)],
            extra_cflags=flags,
            extra_ldflags=["-fopenmp"],
            build_directory=str(build_dir),
            verbose=False,
        )


@contextlib.contextmanager
def _build_guard(build_dir: Path):
    """Serialise loads of one build folder with an OS file lock, and clear a stale torch lock inside it.

    ``cpp_extension.load`` takes a lock of its own (a ``lock`` file it creates and deletes) on every load,
    and waits, forever, while that file exists. A process killed during a load (a node stopped with
    SIGKILL, a test's timeout) leaves the file behind, and every later start hangs silently. The OS
    releases a ``flock`` when its process dies, so while we hold ours, a ``lock`` file can only be such
    a leftover: it is removed with a warning. (Without ``fcntl``, not on Linux: torch's lock alone.)
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - non-POSIX platforms
        yield
        return
    with open(build_dir / "neb_slam.lock", "w") as guard:
        fcntl.flock(guard, fcntl.LOCK_EX)
        try:
            stale = build_dir / "lock"
            if stale.exists():
                log.warning("removing a build lock left by a process killed while loading the extension: %s", stale)
                stale.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(guard, fcntl.LOCK_UN)

