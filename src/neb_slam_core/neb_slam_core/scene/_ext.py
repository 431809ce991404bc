"""Load the map's C++/OpenMP kernels: the module ``neb_slam_core.scene._map_kernels`` (``csrc/map_kernels.cpp``:
the hash-grid, one-blob and decoder kernels, functions on torch tensors that check their arguments).

The module is built when the package is installed: ``setup.py`` compiles it as a torch ``CppExtension``
(into the source tree for an editable install, ``pip install -e``). Compiled into it is its build key
(:func:`build_key`): a hash of the sources, the compiler flags, the torch and Python versions and the CPU
architecture and instruction set. It is used only when that key is the one of the sources beside this
file, on this machine; so a source edited after the install, another torch, or a venv moved to another CPU
never runs a binary built for something else.

Otherwise (no built module: installed without torch at build time, or its build failed; or another key),
the fallback compiles the same source on first use with ``torch.utils.cpp_extension.load`` (ninja, about
a minute) and keeps the binary, named by its key, in a cache folder: first that is set of
``$NEB_SLAM_EXT_DIR``, ``$TORCH_EXTENSIONS_DIR``, ``$XDG_CACHE_HOME/neb_slam/torch_extensions``,
``~/.cache/neb_slam/torch_extensions``. Each such build runs in a fresh temporary folder (torch's own
build lock lives there, where no other process ever waits on it) and its binary is moved into the cache
in one rename; an OS file lock, which the OS releases when its holder dies, makes concurrent processes
wait for one build instead of compiling the same one each.

A failure (no compiler, no ninja, an unsupported platform) is remembered for the rest of the process:
:func:`load_map_kernels` raises :class:`ExtensionUnavailable` with the reason, once built or not.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import importlib.util
import logging
import os
import platform
import sys
import tempfile
import threading
from pathlib import Path
from types import ModuleType

import torch

log = logging.getLogger(__name__)

CSRC = Path(__file__).resolve().parent / "csrc"
SOURCE = CSRC / "map_kernels.cpp"  # the torch binding; it includes the kernels, csrc/*_kernels.h
#: the module that setup.py builds at install
INSTALLED = "neb_slam_core.scene._map_kernels"
#: the fallback's module (and file) name, before ``_<build key>``
JIT_PREFIX = "neb_map_kernels"
#: the macro that carries the build key into the module (its ``build_key`` attribute)
BUILD_KEY_MACRO = "NEB_MAP_KERNELS_BUILD_KEY"

_module: ModuleType | None = None
_failure: str | None = None
_lock = threading.Lock()  # one load (or build) per process even when several threads ask at once


class ExtensionUnavailable(RuntimeError):
    """The fast CPU path could not be built or loaded; ``reason`` says why."""

    def __init__(self, reason: str):
        self.reason = reason
        super().__init__(f"map C++ kernels unavailable: {reason}")


def compile_flags() -> list[str]:
    """Portable optimisation flags, plus AVX2/FMA only when torch reports this CPU supports them (the
    install build and the fallback use the same).

    No ``-march=native``: the build key includes these flags and the CPU capability, so a binary is never
    used on a CPU that lacks what it was built for.
    """
    # -fno-trapping-math lets the compiler turn the clamps and selects of the kernels into branch-free
    # vector code (5x on the cell computation); the kernels never rely on floating-point exceptions.
    flags = ["-O3", "-fopenmp", "-fno-trapping-math"]
    if platform.machine().lower() in ("x86_64", "amd64"):
        capability = torch.backends.cpu.get_cpu_capability()  # "DEFAULT", "AVX2", "AVX512", ...
        if capability in ("AVX2", "AVX512"):
            flags += ["-mavx2", "-mfma"]
    return flags


def build_key(flags: list[str]) -> str:
    """Hash of the sources, flags, torch/Python versions and CPU: names a build (the fallback's file) and is
    compiled into the module (its ``build_key``)."""
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


def key_define(key: str) -> str:
    """The compiler flag that compiles ``key`` in (a hex string: one preprocessor token, no quoting)."""
    return f"-D{BUILD_KEY_MACRO}={key}"


def cache_root() -> Path:
    for var in ("NEB_SLAM_EXT_DIR", "TORCH_EXTENSIONS_DIR"):
        value = os.environ.get(var)
        if value:
            return Path(value).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "neb_slam" / "torch_extensions"


def load_map_kernels() -> ModuleType:
    """The kernels' module: the one built at install when it matches, else the fallback's (compiled on the
    first call of the process when not in the cache yet).

    Raises:
        ExtensionUnavailable: neither could be loaded (the reason is kept for the process).
    """
    global _module, _failure
    if _module is not None:
        return _module
    with _lock:
        if _module is None and _failure is None:
            try:
                _module = _build()
            except Exception as exc:  # compiler error, no ninja, import error: all mean "use the reference"
                log.debug("map C++ kernels: build failed", exc_info=True)
                first_line = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
                _failure = f"{type(exc).__name__}: {first_line}"
        if _module is None:
            raise ExtensionUnavailable(_failure or "unknown")
        return _module


def loaded_from_install(module: ModuleType) -> bool:
    """Whether ``module`` (from :func:`load_map_kernels`) is the one built at install, not the fallback's."""
    return module.__name__ == INSTALLED


def prepare(backend: str) -> None:
    """Load the kernels now (building them if the fallback must) unless ``backend`` is ``"reference"``:
    ``neb-slam run`` does this before its first frame and before its threads start, so that a one-time
    load or compile is not timed as that frame's work. A failure is only remembered here; the modules
    report it where they would use the kernels (``"auto"`` falls back, ``"fast"`` raises)."""
    if backend != "reference":
        unavailable_reason()


def unavailable_reason() -> str | None:
    """Why the kernels cannot be used in this process (loads them if needed), or ``None`` if they can."""
    try:
        load_map_kernels()
    except ExtensionUnavailable as exc:
        return exc.reason
    return None


def use_fast_path(backend: str, eligible: bool, owner: str, needs: str) -> bool:
    """The backend rule of the modules with a C++ path (one-blob, decoders): ``"reference"`` never,
    ``"fast"`` always (an error when the inputs are not ``eligible``, described by ``needs``, or the
    kernels are unavailable), ``"auto"`` when eligible and the kernels load."""
    if backend == "reference":
        return False
    if backend == "fast":
        if not eligible:
            raise ValueError(f"{owner} backend 'fast' needs {needs}")
        try:
            load_map_kernels()
        except ExtensionUnavailable as exc:
            raise RuntimeError(f"{owner} backend 'fast' requested but unavailable: {exc.reason}") from exc
        return True
    return eligible and unavailable_reason() is None


def _build() -> ModuleType:
    """The module built at install when its key is this machine's, else the fallback's."""
    flags = compile_flags()
    key = build_key(flags)
    installed = _installed_module(key)
    return installed if installed is not None else _compile_on_first_use(flags, key)


def _installed_module(key: str) -> ModuleType | None:
    try:
        module = importlib.import_module(INSTALLED)
    except ImportError as exc:
        log.info("map C++ kernels: no module built at install (%s); compiling them on first use", exc)
        return None
    built_for = getattr(module, "build_key", None)
    if built_for != key:
        log.warning(
            "map C++ kernels: %s was built for other sources, flags, torch or CPU (key %s, these need %s): "
            "compiling them on first use; reinstall the package to build them at install",
            module.__file__,
            built_for,
            key,
        )
        return None
    return module


def _compile_on_first_use(flags: list[str], key: str) -> ModuleType:
    """The fallback: the cached binary of this key, compiled first (in a private folder) when absent."""
    from torch.utils import cpp_extension

    if not SOURCE.is_file():
        raise FileNotFoundError(f"kernel source missing: {SOURCE.name} (package data not installed?)")
    name = f"{JIT_PREFIX}_{key}"
    root = cache_root()
    root.mkdir(parents=True, exist_ok=True)
    target = root / f"{name}{getattr(cpp_extension, 'LIB_EXT', '.so')}"
    with _exclusive(root / f"{name}.lock"):
        if not target.is_file():
            log.info("compiling the map's C++ kernels (about a minute, once), cache: %s", target)
            with tempfile.TemporaryDirectory(prefix=f"{name}-", dir=root) as build_dir:
                module = cpp_extension.load(
                    name=name,
                    sources=[str(SOURCE)],
                    extra_cflags=flags + [key_define(key)],
                    extra_ldflags=["-fopenmp"],
                    build_directory=build_dir,
                    verbose=False,
                )
                # torch renames a second build of one name in a process (name_v1): that one is not kept
                if module.__name__ == name:
                    os.replace(Path(build_dir) / target.name, target)  # one rename: never a half-written file
                    module.__file__ = str(target)
            return module
    return _import_file(name, target)


def _import_file(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def _exclusive(lock_path: Path):
    """Hold an OS file lock on ``lock_path`` (released by the OS when the process dies, so a killed build
    never blocks the next one). Without ``fcntl`` (not POSIX): no lock; concurrent builds then each compile,
    and the last rename wins."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - non-POSIX platforms
        yield
        return
    with open(lock_path, "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
