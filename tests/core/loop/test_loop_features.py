"""ORB extraction: typed output, upsampling of small images maps keypoints back to the original pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from neb_slam_core.loop.features import OrbExtractor, OrbParams, to_grey


def checkerboard(width: int, height: int, square_px: int) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB: bright squares of half the cell on a dark ground, one per ``square_px``
    cell (isolated squares have L-shaped corners, which FAST finds; a checkerboard's X junctions it
    does not). Square edges lie between pixels ``k * square_px / 2 - 1`` and ``k * square_px / 2``."""
    v, u = np.mgrid[0:height, 0:width]
    half = square_px // 2
    bright = ((u // half) % 2 == 1) & ((v // half) % 2 == 1)
    grey = np.where(bright, 215, 40).astype(np.uint8)
    grey = cv2.GaussianBlur(grey, (3, 3), 0)  # a camera's slight blur (FAST misses some perfectly sharp corners)
    return np.repeat(grey[..., None], 3, axis=2)


@pytest.mark.parametrize("width,factor", [(160, 2), (320, 1)])
def test_keypoints_sit_on_the_checkerboard_corners_in_original_pixels(width, factor):
    height, square = width * 3 // 4, width // 8
    ex = OrbExtractor(OrbParams(n_features=300, min_width_px=320))
    assert ex.upsample_factor(width) == factor
    f = ex(checkerboard(width, height, square))
    assert len(f) > 20
    assert f.keypoints_px.dtype == np.float32 and f.keypoints_px.shape == (len(f), 2)
    assert f.descriptors.dtype == np.uint8 and f.descriptors.shape == (len(f), 32)
    assert f.octaves.shape == (len(f),) and f.image_size == (width, height)
    # corners of the squares lie half-way between pixels: at k * square / 2 - 0.5
    half = square / 2
    near = np.abs((f.keypoints_px + 0.5) / half - np.round((f.keypoints_px + 0.5) / half)) * half
    level0 = f.octaves == 0
    assert level0.sum() > 10
    # ORB reports these corners 1.5 px (along each axis) inside the bright square of the image it
    # detects on; mapped back from the upsampled image that offset shrinks by the factor
    assert np.median(near[level0], axis=0) == pytest.approx([1.5 / factor] * 2, abs=0.1)


def test_a_mask_and_a_flat_image():
    ex = OrbExtractor(OrbParams(n_features=200))
    img = checkerboard(320, 240, 40)
    mask = np.zeros((240, 320), bool)
    mask[:, :160] = True
    f = ex(img, mask)
    assert len(f) > 0 and f.keypoints_px[:, 0].max() < 160
    flat = ex(np.full((240, 320, 3), 128, np.uint8))
    assert len(flat) == 0 and flat.descriptors.shape == (0, 32) and flat.keypoints_px.shape == (0, 2)


def test_grey_conversion_accepts_rgb_and_grey_only():
    assert to_grey(np.zeros((4, 5), np.uint8)).shape == (4, 5)
    assert to_grey(np.zeros((4, 5, 3), np.uint8)).shape == (4, 5)
    with pytest.raises(ValueError, match="uint8"):
        to_grey(np.zeros((4, 5, 3), np.float32))
    with pytest.raises(ValueError, match="shape"):
        to_grey(np.zeros((4, 5, 4), np.uint8))
