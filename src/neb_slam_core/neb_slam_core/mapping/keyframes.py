"""The keyframe store: a random subset of each keyframe's pixels (as Co-SLAM keeps them), its pose, and
which blocks each keyframe belongs to."""

from __future__ import annotations

import bisect
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import torch

from ..render.rays import PixelSamples, sample_pixels
from ..types import RgbdFrame


@dataclass
class Keyframe:
    """One keyframe.

    Attributes:
        keyframe_id: position in the store.
        frame_index: index of the frame in the input sequence.
        stamp_ns: its time stamp.
        T_world_cam: current pose estimate (float64 4x4), refined by mapping and loop closure.
        pixels: the kept pixels (camera-frame rays with colour and depth).
        block_ids: the blocks it belongs to, ascending (set through :meth:`KeyframeStore.assign`).
    """

    keyframe_id: int
    frame_index: int
    stamp_ns: int
    T_world_cam: np.ndarray
    pixels: PixelSamples
    block_ids: list[int] = field(default_factory=list)

    def observed_points(self) -> np.ndarray:
        """``(K, 3)`` world points of the kept pixels with depth (float64)."""
        px = self.pixels
        ok = px.depth_m > 0
        pts = (px.dirs_cam[ok] * px.depth_m[ok, None]).double().cpu().numpy()
        return pts @ self.T_world_cam[:3, :3].T + self.T_world_cam[:3, 3]


class KeyframeStore:
    """All keyframes, with their pixels concatenated for fast random ray draws, and the index of the
    keyframes that belong to each block (mapping draws its extra N_a rays from the newest block's)."""

    def __init__(self, pixel_fraction: float, seed: int = 0, device: torch.device | str = "cpu"):
        self.pixel_fraction = pixel_fraction
        self.rng = np.random.default_rng(seed)
        self.device = device
        self.keyframes: list[Keyframe] = []
        self._flat: tuple[torch.Tensor, ...] | None = None
        self._block_keyframes: dict[int, list[int]] = {}  # block id -> keyframe ids, ascending

    def __len__(self) -> int:
        return len(self.keyframes)

    def __getitem__(self, i: int) -> Keyframe:
        return self.keyframes[i]

    def add(self, frame: RgbdFrame, T_world_cam: np.ndarray, frame_index: int) -> Keyframe:
        h, w = frame.depth_m.shape
        n = max(1, int(round(self.pixel_fraction * h * w)))
        px = sample_pixels(frame, n, self.rng, valid_depth_only=False, device=self.device)
        kf = Keyframe(len(self.keyframes), frame_index, frame.stamp_ns, np.array(T_world_cam, dtype=np.float64), px)
        self.keyframes.append(kf)
        self._flat = None
        return kf

    def poses(self) -> np.ndarray:
        """``(K, 4, 4)`` current keyframe poses."""
        return np.stack([kf.T_world_cam for kf in self.keyframes])

    def set_poses(self, poses: np.ndarray) -> None:
        for kf, T in zip(self.keyframes, poses):
            kf.T_world_cam = np.array(T, dtype=np.float64)

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

    def flat(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """All kept pixels: dirs_cam (P, 3), rgb (P, 3), depth (P,), keyframe index (P,)."""
        if self._flat is None:
            kfs = self.keyframes
            self._flat = (
                torch.cat([k.pixels.dirs_cam for k in kfs]),
                torch.cat([k.pixels.rgb for k in kfs]),
                torch.cat([k.pixels.depth_m for k in kfs]),
                torch.cat(
                    [torch.full((len(k.pixels),), k.keyframe_id, dtype=torch.long, device=self.device) for k in kfs]
                ),
            )
        return self._flat

    def draw(self, n: int, generator: torch.Generator, keyframe_ids: list[int] | None = None) -> torch.Tensor:
        """Indices into :meth:`flat` of ``n`` random kept pixels (from ``keyframe_ids`` only when given)."""
        _, _, _, owner = self.flat()
        if keyframe_ids is None:
            return torch.randint(len(owner), (n,), generator=generator, device=owner.device)
        pool = torch.isin(owner, torch.as_tensor(keyframe_ids, device=owner.device)).nonzero(as_tuple=True)[0]
        if len(pool) == 0:
            return pool
        return pool[torch.randint(len(pool), (n,), generator=generator, device=owner.device)]
