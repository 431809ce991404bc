"""The keyframe store: a random subset of each keyframe's pixels (as Co-SLAM keeps them), its pose, and
which blocks each keyframe belongs to.

Which pixels a keyframe keeps comes from one random order of all pixels of its image size, drawn once
per size and shared by the keyframes: a keyframe keeps the ``n`` pixels that follow a random offset in
that order (wrapping round), so every pixel is kept with the same chance ``pixel_fraction`` and no
pixel twice, and the keyframe stores its offset instead of its pixels' coordinates. Colour (uint8) and
depth (float16: 0.05 % of the depth, far below any depth sensor's noise) of the kept pixels live in two
flat buffers, 5 bytes per pixel, a keyframe being a range of them. Coordinates come back from the
order, and ray directions from the coordinates and the keyframe's intrinsics, when pixels are drawn. So
the store grows by ``5 * pixel_fraction * width * height`` bytes per keyframe (77 KB at 640x480 and
the default 5 %), plus 4 bytes per pixel of each image size once for its order. The buffers grow by a
quarter when full: at most a quarter of them is spare, and each pixel is copied four times over a run
on average.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import torch

from ..types import Intrinsics, RgbdFrame

#: bytes the store keeps per kept pixel: colour (3 x uint8), depth (float16)
BYTES_PER_PIXEL = 3 + 2
#: bytes of an image size's pixel order, per pixel of the image: (u, v) as 2 x int16
ORDER_BYTES_PER_PIXEL = 2 * 2
#: how much the pixel buffers grow when full
GROWTH = 1.25


@dataclass
class Keyframe:
    """One keyframe.

    Attributes:
        keyframe_id: position in the store.
        frame_index: index of the frame in the input sequence.
        stamp_ns: its time stamp.
        T_world_cam: current pose estimate (float64 4x4), refined by mapping and loop closure.
        intrinsics: its (rectified, pinhole) camera.
        start, n_pixels: its kept pixels are ``start .. start + n_pixels`` of the store's buffers.
        order_offset: its first kept pixel's position in its image size's pixel order.
        block_ids: the blocks it belongs to, ascending (set through :meth:`KeyframeStore.assign`).
    """

    keyframe_id: int
    frame_index: int
    stamp_ns: int
    T_world_cam: np.ndarray
    intrinsics: Intrinsics
    start: int
    n_pixels: int
    order_offset: int
    block_ids: list[int] = field(default_factory=list)


class KeyframeStore:
    """All keyframes, their kept pixels in flat buffers for fast random ray draws (module docstring), and
    the index of the keyframes that belong to each block (mapping draws its extra N_a rays from the
    newest block's)."""

    def __init__(self, pixel_fraction: float, seed: int = 0, device: torch.device | str = "cpu"):
        self.pixel_fraction = pixel_fraction
        self.rng = np.random.default_rng(seed)
        self.device = device
        self.keyframes: list[Keyframe] = []
        self._n = 0  # pixels in use
        # every image size's pixels in a random order, one size after another: (u, v) rows
        self._orders_uv = torch.zeros((0, 2), dtype=torch.int16, device=device)
        self._order_start: dict[tuple[int, int], int] = {}  # (height, width) -> its first row in _orders_uv
        self._rgb = torch.zeros((0, 3), dtype=torch.uint8, device=device)
        self._depth = torch.zeros(0, dtype=torch.float16, device=device)
        self._starts = torch.zeros(0, dtype=torch.long, device=device)  # per keyframe, its first pixel
        self._camera = torch.zeros((0, 4), dtype=torch.float32, device=device)  # per keyframe fx, fy, cx, cy
        # per keyframe: its order's first row in _orders_uv, the order's length, the keyframe's offset in it
        self._window = torch.zeros((0, 3), dtype=torch.long, device=device)
        self._block_keyframes: dict[int, list[int]] = {}  # block id -> keyframe ids, ascending

    def __len__(self) -> int:
        return len(self.keyframes)

    def __getitem__(self, i: int) -> Keyframe:
        return self.keyframes[i]

    @property
    def n_pixels(self) -> int:
        """Kept pixels of all keyframes."""
        return self._n

    def nbytes(self) -> int:
        """Bytes the store holds: pixel buffers (with their spare capacity), pixel orders and per-keyframe
        records."""
        buffers = (self._orders_uv, self._rgb, self._depth, self._starts, self._camera, self._window)
        poses = 16 * 8 * len(self.keyframes)
        index = 8 * sum(len(kf.block_ids) for kf in self.keyframes)
        return sum(t.element_size() * t.nelement() for t in buffers) + poses + 2 * index

    def add(self, frame: RgbdFrame, T_world_cam: np.ndarray, frame_index: int) -> Keyframe:
        h, w = frame.depth_m.shape
        if max(h, w) > np.iinfo(np.int16).max:
            raise ValueError(f"KeyframeStore: a {w}x{h} image has coordinates beyond int16")
        n = max(1, int(round(self.pixel_fraction * h * w)))
        d = self.device
        order_start = self._order(h, w)  # first: a new image size draws its order from the same generator
        offset = int(self.rng.integers(h * w))
        window = torch.tensor([order_start, h * w, offset], device=d)
        uv = self._orders_uv[_order_rows(window, torch.arange(n, device=d))].long().cpu().numpy()
        pick = uv[:, 1] * w + uv[:, 0]
        start = self._n
        self._reserve(start + n)
        self._rgb[start : start + n] = torch.as_tensor(frame.rgb.reshape(-1, 3)[pick], device=d)
        self._depth[start : start + n] = torch.as_tensor(frame.depth_m.reshape(-1)[pick], device=d).half()
        self._n = start + n
        k = frame.intrinsics
        self._starts = torch.cat([self._starts, torch.tensor([start], device=d)])
        self._camera = torch.cat([self._camera, torch.tensor([[k.fx, k.fy, k.cx, k.cy]], device=d)])
        self._window = torch.cat([self._window, window[None]])
        T = np.array(T_world_cam, dtype=np.float64)
        kf = Keyframe(len(self.keyframes), frame_index, frame.stamp_ns, T, k, start, n, offset)
        self.keyframes.append(kf)
        return kf

    def _order(self, h: int, w: int) -> int:
        """The first row in the pixel orders of the ``h x w`` size's order, drawn when first needed."""
        if (h, w) not in self._order_start:
            v, u = np.divmod(self.rng.permutation(h * w), w)
            order = torch.as_tensor(np.stack([u, v], axis=1).astype(np.int16), device=self.device)
            self._order_start[(h, w)] = len(self._orders_uv)
            self._orders_uv = torch.cat([self._orders_uv, order])
        return self._order_start[(h, w)]

    def _reserve(self, n: int) -> None:
        """Grow the pixel buffers (by :data:`GROWTH`) to hold ``n`` pixels."""
        if n <= len(self._depth):
            return
        cap = max(n, int(GROWTH * len(self._depth)))

        def grown(t: torch.Tensor) -> torch.Tensor:
            out = torch.empty((cap, *t.shape[1:]), dtype=t.dtype, device=t.device)
            out[: self._n] = t[: self._n]
            return out

        self._rgb, self._depth = grown(self._rgb), grown(self._depth)

    def poses(self) -> np.ndarray:
        """``(K, 4, 4)`` current keyframe poses."""
        return np.stack([kf.T_world_cam for kf in self.keyframes])

    def set_poses(self, poses: np.ndarray) -> None:
        for kf, T in zip(self.keyframes, poses):
            kf.T_world_cam = np.array(T, dtype=np.float64)

    # ------------------------------------------------------------------ pixels

    def gather(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The kept pixels ``idx`` (indices into all keyframes' pixels, as :meth:`draw` gives them):
        camera-frame directions ``(N, 3)`` (z = 1), colour in [0, 1] ``(N, 3)``, depth ``(N,)`` and the
        keyframe id of each ``(N,)``."""
        owner = torch.searchsorted(self._starts, idx, right=True) - 1
        cam = self._camera[owner]
        uv = self._orders_uv[_order_rows(self._window[owner], idx - self._starts[owner])].to(torch.float32)
        x = (uv[:, 0] - cam[:, 2]) / cam[:, 0]
        y = (uv[:, 1] - cam[:, 3]) / cam[:, 1]
        dirs = torch.stack([x, y, torch.ones_like(x)], dim=-1)
        return dirs, self._rgb[idx].float() / 255.0, self._depth[idx].float(), owner

    def draw(self, n: int, generator: torch.Generator, keyframe_ids: list[int] | None = None) -> torch.Tensor:
        """Indices of ``n`` random kept pixels, for :meth:`gather` (of ``keyframe_ids`` only when given;
        empty when they hold none)."""
        if keyframe_ids is None:
            return torch.randint(self._n, (n,), generator=generator, device=self.device)
        kfs = [self.keyframes[i] for i in keyframe_ids]
        counts = torch.tensor([kf.n_pixels for kf in kfs], dtype=torch.long, device=self.device)
        total = int(counts.sum()) if len(kfs) else 0
        if total == 0:
            return torch.zeros(0, dtype=torch.long, device=self.device)
        # a draw from the keyframes' pixels as one pool: the pool position -> (keyframe, offset in it)
        j = torch.randint(total, (n,), generator=generator, device=self.device)
        ends = torch.cumsum(counts, 0)
        which = torch.searchsorted(ends, j, right=True)
        starts = torch.tensor([kf.start for kf in kfs], dtype=torch.long, device=self.device)
        return starts[which] + j - (ends[which] - counts[which])

    def observed_points(self, kf: Keyframe) -> np.ndarray:
        """``(K, 3)`` world points of ``kf``'s kept pixels with depth (float64)."""
        idx = torch.arange(kf.start, kf.start + kf.n_pixels, device=self.device)
        dirs, _, depth, _ = self.gather(idx)
        ok = depth > 0
        pts = (dirs[ok] * depth[ok, None]).double().cpu().numpy()
        return pts @ kf.T_world_cam[:3, :3].T + kf.T_world_cam[:3, 3]

    # ------------------------------------------------------------------ blocks

    def assign(self, kf: Keyframe, block_ids: Iterable[int]) -> None:
        """Make ``kf`` a keyframe of exactly the blocks ``block_ids``, replacing what it belonged to before
        (a keyframe moved by a loop correction is reassigned to the blocks its points now fall in). Both
        sides stay ascending: ``kf.block_ids`` and each block's keyframe ids."""
        for block_id in kf.block_ids:
            self._block_keyframes[block_id].remove(kf.keyframe_id)
        kf.block_ids = sorted(set(int(b) for b in block_ids))
        for block_id in kf.block_ids:
            bisect.insort(self._block_keyframes.setdefault(block_id, []), kf.keyframe_id)

    def keyframes_of_block(self, block_id: int) -> list[int]:
        """Ids of the keyframes that belong to block ``block_id``, ascending (empty: none)."""
        return list(self._block_keyframes.get(block_id, ()))

    def block_keyframes(self) -> dict[int, list[int]]:
        """The whole index: block id -> ids of its keyframes, ascending (blocks without keyframes left out)."""
        return {b: list(ids) for b, ids in sorted(self._block_keyframes.items()) if ids}


def _order_rows(window: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
    """The rows of the pixel orders that hold kept pixels ``local`` (0 = a keyframe's first) of keyframes
    whose ``window`` is (its order's first row, the order's length, the keyframe's offset in it); ``window``
    ``(3,)`` for one keyframe or ``(N, 3)`` with ``local`` ``(N,)``."""
    return window[..., 0] + (window[..., 2] + local) % window[..., 1]
