"""ORB keypoints and binary descriptors of one image (OpenCV), the input of place recognition.

ORB (oriented FAST corners, rotated BRIEF descriptors) gives 256-bit binary descriptors, stored as
``(N, 32)`` uint8 rows; two descriptors are compared by their Hamming distance (bits that differ).

Small images: ORB describes a keypoint by a ``patch_size_px`` (31 px) patch and ignores keypoints
closer than that to the border, so at 160x120 (the synthetic demo scenes) most of the image is lost and
the coarse pyramid levels are smaller than a patch. Images narrower than ``min_width_px`` are therefore
upsampled by an integer factor before detection, and keypoints are mapped back to the original pixels.

Pixel convention (as everywhere in the project): integer ``(u, v)`` are pixel centres. OpenCV's
keypoints follow it, and ``cv2.resize`` by a factor ``s`` maps source centre ``x`` to ``(x + 0.5) s - 0.5``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

#: bytes per ORB descriptor (256 bits)
DESCRIPTOR_BYTES = 32


@dataclass(frozen=True)
class OrbParams:
    """ORB detector settings (OpenCV's names in brackets).

    Attributes:
        n_features: keypoints kept per image at most (``nfeatures``), strongest by FAST/Harris response.
        scale_factor: pyramid scale between levels (``scaleFactor``).
        n_levels: pyramid levels (``nlevels``).
        fast_threshold: FAST intensity threshold (``fastThreshold``, grey levels 0..255).
        min_width_px: images narrower than this are upsampled (integer factor) before detection.
    """

    n_features: int = 1000
    scale_factor: float = 1.2
    n_levels: int = 8
    fast_threshold: int = 20
    min_width_px: int = 320


@dataclass(frozen=True)
class OrbFeatures:
    """Keypoints and descriptors of one image.

    Attributes:
        keypoints_px: ``(N, 2)`` float32 ``(u, v)`` in the original image's pixels (pixel centres).
        descriptors: ``(N, 32)`` uint8 ORB descriptors, row ``i`` belongs to keypoint ``i``.
        octaves: ``(N,)`` int16 pyramid level each keypoint was found at.
        image_size: ``(width, height)`` of the image they come from.
    """

    keypoints_px: np.ndarray
    descriptors: np.ndarray
    octaves: np.ndarray
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.keypoints_px)

    @staticmethod
    def empty(image_size: tuple[int, int]) -> OrbFeatures:
        return OrbFeatures(
            np.zeros((0, 2), np.float32), np.zeros((0, DESCRIPTOR_BYTES), np.uint8), np.zeros(0, np.int16), image_size
        )


def to_grey(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB (the project's colour convention) or ``(H, W)`` grey -> ``(H, W)`` uint8 grey."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"ORB needs uint8 images, got {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    raise ValueError(f"expected an (H, W, 3) RGB or (H, W) grey image, got shape {image.shape}")


class OrbExtractor:
    """Extracts :class:`OrbFeatures` from images with fixed :class:`OrbParams` (one OpenCV detector, reused)."""

    def __init__(self, params: OrbParams = OrbParams()):
        self.params = params
        self._orb = cv2.ORB_create(
            nfeatures=params.n_features,
            scaleFactor=params.scale_factor,
            nlevels=params.n_levels,
            fastThreshold=params.fast_threshold,
        )

    def __getstate__(self) -> dict:  # OpenCV's detector does not pickle: it is made again from the params
        return {"params": self.params}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["params"])

    def upsample_factor(self, width_px: int) -> int:
        """The integer factor an image ``width_px`` wide is upsampled by before detection (1 = none)."""
        return max(1, math.ceil(self.params.min_width_px / max(1, width_px)))

    def __call__(self, image: np.ndarray, mask: np.ndarray | None = None) -> OrbFeatures:
        """Features of ``image`` (``(H, W, 3)`` uint8 RGB or ``(H, W)`` grey).

        Args:
            mask: optional ``(H, W)`` bool/uint8; keypoints only where it is non-zero.
        """
        grey = to_grey(image)
        h, w = grey.shape
        s = self.upsample_factor(w)
        if s > 1:
            grey = cv2.resize(grey, (w * s, h * s), interpolation=cv2.INTER_LINEAR)
            if mask is not None:
                mask = cv2.resize(np.asarray(mask, np.uint8), (w * s, h * s), interpolation=cv2.INTER_NEAREST)
        if mask is not None:
            mask = (np.asarray(mask) != 0).astype(np.uint8)
        keypoints, descriptors = self._orb.detectAndCompute(grey, mask)
        if descriptors is None or not keypoints:
            return OrbFeatures.empty((w, h))
        pts = np.array([kp.pt for kp in keypoints], dtype=np.float32).reshape(-1, 2)
        if s > 1:
            pts = (pts + 0.5) / s - 0.5  # back to the original image's pixel centres
        octaves = np.array([kp.octave for kp in keypoints], dtype=np.int16)
        return OrbFeatures(pts, np.ascontiguousarray(descriptors, dtype=np.uint8), octaves, (w, h))
