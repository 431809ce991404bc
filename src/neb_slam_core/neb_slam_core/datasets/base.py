"""The dataset interface, the loader registry and helpers every loader shares.

A loader is a :class:`Dataset`: it indexes its files when constructed (cheap) and reads one frame per
``__getitem__`` (lazy). Loaders register themselves under a format name with :func:`register`;
:func:`open_dataset` opens a path by name or by asking each loader whether it recognises the layout.

A frame whose colour or depth cannot be read raises :class:`~neb_slam_core.errors.UnreadableFrameError`
(every loader: the shared image readers below raise it, the bag loader raises it for a message that
does not decode), so that a caller decides in one place, for every format, whether to skip the frame:
:class:`FrameSkipper` does that and reports the skipped frames in one warning.
"""

from __future__ import annotations

import inspect
import logging
import re
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import ConfigError, DatasetError, UnreadableFrameError
from ..types import Intrinsics, RgbdFrame

log = logging.getLogger(__name__)


class Dataset(ABC, Sequence[RgbdFrame]):
    """A sequence of RGB-D frames with lazy reading.

    Subclasses set ``self.root`` and implement ``__len__`` and :meth:`_load`; indexing checks bounds,
    supports negative indices, and stamps the frame's ``index``.
    """

    #: format name under which the loader is registered (set by :func:`register`)
    name: str = ""
    root: Path

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def _load(self, i: int) -> RgbdFrame:
        """Read frame ``i`` (0 <= i < len)."""

    @classmethod
    def detect(cls, path: Path) -> bool:
        """True when ``path`` looks like this loader's layout (used by :func:`open_dataset`)."""
        return False

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"{self.name} dataset {self.root}: frame {i} out of range (0..{n - 1})")
        i = i % n
        try:
            frame = self._load(i)
        except UnreadableFrameError as exc:
            exc.index = i
            raise
        frame.index = i
        return frame

    def __iter__(self) -> Iterator[RgbdFrame]:
        for i in range(len(self)):
            yield self[i]

    @property
    def has_ground_truth(self) -> bool:
        """Whether frames carry ``T_world_cam``; loaders with optional ground truth override this."""
        return True

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.root} ({len(self)} frames)>"


_REGISTRY: dict[str, type[Dataset]] = {}


def register(name: str) -> Callable[[type[Dataset]], type[Dataset]]:
    """Class decorator: register a loader under ``name`` (lower case, e.g. ``'tum'``)."""

    def deco(cls: type[Dataset]) -> type[Dataset]:
        if name in _REGISTRY and _REGISTRY[name] is not cls:
            raise ValueError(f"dataset format {name!r} registered twice")
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return deco


def dataset_formats() -> list[str]:
    """Names of all registered formats."""
    _import_loaders()
    return sorted(_REGISTRY)


def loader_class(name: str) -> type[Dataset]:
    _import_loaders()
    try:
        return _REGISTRY[name.lower()]
    except KeyError:
        raise DatasetError(
            None, f"unknown dataset format {name!r}; choose one of: {', '.join(sorted(_REGISTRY))}"
        ) from None


def open_dataset(path: str | Path, fmt: str | None = None, **options) -> Dataset:
    """Open ``path`` with the loader ``fmt``, or detect the format from the layout when ``fmt`` is None;
    ``options`` are keyword arguments of the loader's constructor (a name it lacks is a :class:`DatasetError`)."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(path, "no such file or directory")
    if fmt is not None:
        return _opened(loader_class(fmt), path, options)
    _import_loaders()
    matches = [cls for cls in _REGISTRY.values() if cls.detect(path)]
    if not matches:
        raise DatasetError(
            path, f"cannot tell the dataset format from the layout; pass one of: {', '.join(sorted(_REGISTRY))}"
        )
    if len(matches) > 1:
        names = ", ".join(sorted(cls.name for cls in matches))
        raise DatasetError(path, f"layout matches several formats ({names}); pass the format explicitly")
    return _opened(matches[0], path, options)


def _opened(cls: type[Dataset], path: Path, options: dict) -> Dataset:
    takes = [name for name in inspect.signature(cls.__init__).parameters if name not in ("self", "root")]
    unknown = sorted(set(options) - set(takes))
    if unknown:
        raise DatasetError(
            path, f"the {cls.name} loader has no option {', '.join(unknown)} (it takes: {', '.join(takes) or 'none'})"
        )
    return cls(path, **options)


def _import_loaders() -> None:
    """Import the loader modules so that they register (kept lazy: rosbags is only needed for bags)."""
    from . import _all  # noqa: F401


# ----------------------------------------------------------------------------------------------
# helpers shared by the loaders


def read_rgb(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a colour image as ``(H, W, 3)`` uint8 RGB; resize (area) to ``size`` = (W, H) when given.

    A missing or undecodable file (truncated, say) raises :class:`UnreadableFrameError`; an image of the
    wrong kind raises :class:`DatasetError`.
    """
    # a missing file is caught before OpenCV, which would print a warning of its own for each one
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if Path(path).is_file() else None
    if img is None:
        raise UnreadableFrameError(path, "colour image missing or unreadable (expected an 8-bit PNG/JPEG)")
    if img.dtype != np.uint8:
        raise DatasetError(path, f"colour image must be 8-bit, got {img.dtype}")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img)


def read_depth(
    path: Path, scale: float, invalid_value: int | None = None, expected_size: tuple[int, int] | None = None
) -> np.ndarray:
    """Read a 16-bit depth PNG as float32 metres (``value / scale``; 0 and ``invalid_value`` -> 0).

    ``expected_size`` = (W, H) is checked when given. A missing or undecodable file (truncated, say)
    raises :class:`UnreadableFrameError`; an image of the wrong kind or size raises :class:`DatasetError`.
    """
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if Path(path).is_file() else None
    if raw is None:
        raise UnreadableFrameError(path, "depth image missing or unreadable (expected a 16-bit single-channel PNG)")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        shape = "x".join(map(str, raw.shape))
        raise DatasetError(path, f"depth image must be 16-bit single-channel, got {raw.dtype} with shape {shape}")
    if expected_size is not None and (raw.shape[1], raw.shape[0]) != tuple(expected_size):
        raise DatasetError(
            path, f"depth image is {raw.shape[1]}x{raw.shape[0]}, expected {expected_size[0]}x{expected_size[1]}"
        )
    depth = raw.astype(np.float32) / np.float32(scale)
    if invalid_value is not None:
        depth[raw == invalid_value] = 0.0
    return depth


def read_matrix(path: Path, shape: tuple[int, ...], what: str) -> np.ndarray:
    """Read whitespace-separated numbers from ``path`` into an array of ``shape``."""
    if not path.is_file():
        raise DatasetError(path, f"{what} file not found")
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except ValueError:
        raise DatasetError(path, f"{what}: expected whitespace-separated numbers") from None
    if values.size != int(np.prod(shape)):
        raise DatasetError(
            path, f"{what}: expected {int(np.prod(shape))} numbers ({'x'.join(map(str, shape))}), got {values.size}"
        )
    return values.reshape(shape)


def read_number_rows(path: Path, n_per_line: int, what: str, missing: str) -> list[tuple[int, np.ndarray]]:
    """Read a text file of ``n_per_line`` numbers per non-empty line -> [(line number, values)].

    ``what`` describes one line for error messages (e.g. 'a row-major 4x4'); ``missing`` is the
    message when the file does not exist.
    """
    if not path.is_file():
        raise DatasetError(path, missing)
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = np.array(line.split(), dtype=np.float64)
        except ValueError:
            raise DatasetError(path, f"line {lineno}: expected {n_per_line} numbers, got {line.strip()!r}") from None
        if values.size != n_per_line:
            raise DatasetError(path, f"line {lineno}: expected {n_per_line} numbers ({what}), got {values.size}")
        rows.append((lineno, values))
    return rows


#: Which capture time stamps a frame whose colour and depth images were taken at different times (a
#: sensor that does not synchronise them, such as TUM's Kinect: up to 20 ms apart). ``depth``: the depth
#: image fixes the frame's geometry, which decides most of the tracked pose, so the pose is the camera's
#: at the depth image's time; ``colour``: the colour image's time (what the TUM tools and most RGB-D SLAM
#: evaluations use).
FRAME_STAMPS = ("depth", "colour")


def check_frame_stamp(where: str | Path | None, frame_stamp: str) -> str:
    """``frame_stamp`` if it is one of :data:`FRAME_STAMPS`; else a :class:`DatasetError` at ``where``."""
    if frame_stamp not in FRAME_STAMPS:
        raise DatasetError(where, f"frame_stamp must be one of {', '.join(FRAME_STAMPS)}, got {frame_stamp!r}")
    return frame_stamp


def frame_stamps(colour_ns, depth_ns, frame_stamp: str):
    """The stamps of paired frames (int64 arrays or ints) by ``frame_stamp`` (:data:`FRAME_STAMPS`)."""
    return depth_ns if frame_stamp == "depth" else colour_ns


def associate(query_ns: np.ndarray, ref_ns: np.ndarray, max_dt_ns: int) -> np.ndarray:
    """For each query stamp, the index of the nearest reference stamp within ``max_dt_ns``, else -1.

    Both arrays are int64 nanoseconds; ``ref_ns`` need not be sorted.
    """
    query_ns = np.asarray(query_ns, dtype=np.int64)
    ref_ns = np.asarray(ref_ns, dtype=np.int64)
    if len(ref_ns) == 0:
        return np.full(len(query_ns), -1, dtype=np.int64)
    order = np.argsort(ref_ns, kind="stable")
    ref_sorted = ref_ns[order]
    pos = np.searchsorted(ref_sorted, query_ns)
    lo = np.clip(pos - 1, 0, len(ref_sorted) - 1)
    hi = np.clip(pos, 0, len(ref_sorted) - 1)
    pick = np.where(np.abs(ref_sorted[hi] - query_ns) < np.abs(query_ns - ref_sorted[lo]), hi, lo)
    ok = np.abs(ref_sorted[pick] - query_ns) <= max_dt_ns
    return np.where(ok, order[pick], -1)


def associate_unique(query_ns: np.ndarray, ref_ns: np.ndarray, max_dt_ns: int) -> np.ndarray:
    """Like :func:`associate` but each reference is used at most once (greedy by time gap).

    This is the TUM benchmark's ``associate.py`` rule: candidate pairs within ``max_dt_ns`` are taken
    in order of increasing gap, skipping pairs whose query or reference is already matched.
    """
    query_ns = np.asarray(query_ns, dtype=np.int64)
    ref_ns = np.asarray(ref_ns, dtype=np.int64)
    out = np.full(len(query_ns), -1, dtype=np.int64)
    if len(query_ns) == 0 or len(ref_ns) == 0:
        return out
    order = np.argsort(ref_ns, kind="stable")
    ref_sorted = ref_ns[order]
    # candidates: every reference within the window of each query (windows are short, so few per query)
    lo = np.searchsorted(ref_sorted, query_ns - max_dt_ns, side="left")
    hi = np.searchsorted(ref_sorted, query_ns + max_dt_ns, side="right")
    counts = hi - lo
    qi = np.repeat(np.arange(len(query_ns)), counts)
    ri = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi)]) if counts.sum() else np.zeros(0, np.int64)
    gaps = np.abs(ref_sorted[ri] - query_ns[qi])
    used_ref = np.zeros(len(ref_ns), dtype=bool)
    for k in np.argsort(gaps, kind="stable"):
        q, r = qi[k], ri[k]
        if out[q] < 0 and not used_ref[r]:
            out[q] = order[r]
            used_ref[r] = True
    return out


def warn_skipped(root: Path, n_skipped: int, n_total: int, why: str) -> None:
    """One summary warning for frames a loader skipped (never one warning per frame)."""
    if n_skipped:
        log.warning("%s: skipped %d of %d frames: %s", root, n_skipped, n_total, why)


class FrameSkipper:
    """Reads frames of a dataset by index and skips those whose colour or depth cannot be read.

    :meth:`read` returns None for such a frame and keeps its :class:`UnreadableFrameError`;
    :meth:`warn` then reports all of them in one warning naming each file (a run over a damaged
    recording gets one summary, not a warning per frame). Every other error propagates.
    """

    #: skipped frames named one by one in the warning; the rest are counted
    MAX_NAMED = 20

    def __init__(self, dataset: Dataset):
        self.dataset = dataset
        self.unreadable: list[UnreadableFrameError] = []

    def read(self, i: int) -> RgbdFrame | None:
        """Frame ``i``, or None (recorded) when its colour or depth cannot be read."""
        try:
            return self.dataset[i]
        except UnreadableFrameError as exc:
            self.unreadable.append(exc)
            return None

    def __len__(self) -> int:
        """How many frames were skipped so far."""
        return len(self.unreadable)

    def warn(self) -> None:
        """One warning naming the skipped frames' files (nothing when none was skipped)."""
        if not self.unreadable:
            return
        named = [f"frame {exc.index}: {exc}" for exc in self.unreadable[: self.MAX_NAMED]]
        more = len(self.unreadable) - len(named)
        log.warning(
            "%s: skipped %d frame%s whose colour or depth could not be read: %s%s",
            self.dataset.root,
            len(self.unreadable),
            "" if len(self.unreadable) == 1 else "s",
            "; ".join(named),
            f"; and {more} more" if more else "",
        )


def check_intrinsics(intr: Intrinsics, source: Path | str) -> Intrinsics:
    if not (intr.fx > 0 and intr.fy > 0 and intr.width > 0 and intr.height > 0):
        raise DatasetError(source, f"invalid intrinsics {intr}")
    return intr


def numbered_files(folder: Path, pattern: str, what: str) -> dict[int, Path]:
    """Files of ``folder`` whose whole name matches ``pattern``, keyed by frame number, in numeric order.

    ``pattern`` is a regular expression whose first group is the frame number (``r"frame(\\d+)\\.jpg"``).
    Sorting by the number, not the name, keeps ``10.jpg`` after ``9.jpg``.
    """
    if not folder.is_dir():
        raise DatasetError(folder, f"{what} folder not found")
    rx = re.compile(pattern)
    found: dict[int, Path] = {}
    for path in folder.iterdir():
        m = rx.fullmatch(path.name)
        if m is None:
            continue
        n = int(m.group(1))
        if n in found:
            raise DatasetError(path, f"{what}: frame number {n} is also used by {found[n].name}")
        found[n] = path
    return dict(sorted(found.items()))


def fps_stamp_ns(frame_number: int, fps: float) -> int:
    """Stamp of a frame of a sequence without time stamps: ``frame_number / fps`` seconds, in integer ns."""
    return int(round(frame_number * 1e9 / fps))


def check_fps(fps: float) -> float:
    """``fps`` as a float; :class:`ConfigError` unless it is a finite positive number."""
    try:
        value = float(fps)
    except (TypeError, ValueError):
        value = float("nan")
    if not (0.0 < value < float("inf")):
        raise ConfigError(f"fps must be a positive number of frames per second, got {fps!r}")
    return value


@dataclass(frozen=True)
class FrameFiles:
    """Where one frame of a :class:`FrameListDataset` lives, with its stamp and pose (``(4, 4)`` or None)."""

    rgb_path: Path
    depth_path: Path
    stamp_ns: int
    T_world_cam: np.ndarray | None


class FrameListDataset(Dataset):
    """A loader whose ``__init__`` lists its frames as :class:`FrameFiles` and whose frames read alike.

    Subclasses set ``root``, ``intrinsics``, ``depth_scale`` (raw value per metre), ``frames`` and, when
    they apply, ``depth_invalid_value`` and ``resize_rgb`` (colour resized to the depth size, area
    interpolation; otherwise a colour image of another size is an error).
    """

    intrinsics: Intrinsics
    depth_scale: float
    depth_invalid_value: int | None = None
    resize_rgb: bool = False
    frames: list[FrameFiles]

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def stamps_ns(self) -> np.ndarray:
        """``(N,)`` int64 stamps of the frames."""
        return np.array([f.stamp_ns for f in self.frames], dtype=np.int64)

    def _load(self, i: int) -> RgbdFrame:
        f = self.frames[i]
        size = (self.intrinsics.width, self.intrinsics.height)
        depth = read_depth(f.depth_path, self.depth_scale, self.depth_invalid_value, expected_size=size)
        rgb = read_rgb(f.rgb_path, size if self.resize_rgb else None)
        if (rgb.shape[1], rgb.shape[0]) != size:
            raise DatasetError(
                f.rgb_path,
                f"colour image is {rgb.shape[1]}x{rgb.shape[0]}, expected {size[0]}x{size[1]} "
                "(the size of the intrinsics)",
            )
        pose = None if f.T_world_cam is None else f.T_world_cam.copy()
        return RgbdFrame(rgb, depth, self.intrinsics, f.stamp_ns, pose)


def pair_by_number(root: Path, rgb_files: dict[int, Path], depth_files: dict[int, Path]) -> list[int]:
    """Numbers of the colour frames that have a depth image of the same number, in order.

    Colour frames without a depth partner are dropped with one summary warning.
    """
    keep = [n for n in rgb_files if n in depth_files]
    warn_skipped(
        root, len(rgb_files) - len(keep), len(rgb_files), "colour images with no depth image of the same number"
    )
    return keep


def poses_by_image_order(poses: Sequence, rgb_files: dict[int, Path], pose_path: Path, folder: str) -> dict:
    """Give the k-th pose of ``pose_path`` to the k-th colour image (in number order): ``{number: pose}``.

    Raises :class:`DatasetError` naming ``pose_path`` when the counts differ.
    """
    if len(poses) != len(rgb_files):
        raise DatasetError(
            pose_path,
            f"{len(poses)} poses for {len(rgb_files)} colour images in {folder}/; expected one pose per colour image",
        )
    return dict(zip(rgb_files, poses))
