"""The keyframe store: its kept pixels, its draws, its size, and its block index (which keyframes belong to
which block)."""

from __future__ import annotations

import numpy as np
import torch

from neb_slam_core.mapping.keyframes import KeyframeStore
from neb_slam_core.types import Intrinsics, RgbdFrame


def store_with(n: int) -> KeyframeStore:
    k = Intrinsics(20.0, 20.0, 8.0, 6.0, 16, 12)
    store = KeyframeStore(0.1, seed=0)
    for i in range(n):
        frame = RgbdFrame(np.zeros((12, 16, 3), np.uint8), np.full((12, 16), 2.0, np.float32), k, i)
        store.add(frame, np.eye(4), i)
    return store


def test_assign_keeps_both_sides_ascending_and_reassigning_replaces():
    store = store_with(4)
    kfs = store.keyframes
    store.assign(kfs[0], [0])
    store.assign(kfs[1], [2, 0])
    store.assign(kfs[3], [0, 1])
    assert kfs[1].block_ids == [0, 2]
    assert store.keyframes_of_block(0) == [0, 1, 3] and store.keyframes_of_block(2) == [1]
    # a keyframe moved back (a loop correction) lands in its place, not at the end
    store.assign(kfs[2], [1, 2])
    assert store.keyframes_of_block(1) == [2, 3] and store.keyframes_of_block(2) == [1, 2]
    store.assign(kfs[1], [1])
    assert kfs[1].block_ids == [1]
    assert store.keyframes_of_block(0) == [0, 3] and store.keyframes_of_block(1) == [1, 2, 3]
    assert store.keyframes_of_block(2) == [2] and store.keyframes_of_block(7) == []
    store.assign(kfs[2], [])
    assert store.block_keyframes() == {0: [0, 3], 1: [1, 3]}
    store.keyframes_of_block(0).append(9)  # a copy: the index is changed through assign only
    assert store.keyframes_of_block(0) == [0, 3]


def _pixels(dirs: torch.Tensor, k: Intrinsics) -> tuple[torch.Tensor, torch.Tensor]:
    """The pixel ``(u, v)`` of each gathered direction (z = 1) of a camera ``k``."""
    return torch.round(dirs[:, 0] * k.fx + k.cx).long(), torch.round(dirs[:, 1] * k.fy + k.cy).long()


def _textured_store(n_keyframes: int, pixel_fraction: float = 0.25) -> tuple[KeyframeStore, list[RgbdFrame]]:
    k = Intrinsics(20.0, 22.0, 7.5, 5.5, 16, 12)
    rng = np.random.default_rng(7)
    store, frames = KeyframeStore(pixel_fraction, seed=3), []
    for i in range(n_keyframes):
        rgb = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
        depth = rng.uniform(0.5, 4.0, (12, 16)).astype(np.float32)
        frames.append(RgbdFrame(rgb, depth, k, i))
        store.add(frames[-1], np.eye(4), i)
    return store, frames


def test_gather_gives_each_kept_pixel_of_its_keyframe():
    store, frames = _textured_store(5)
    n = store[0].n_pixels
    assert n == round(0.25 * 16 * 12) and store.n_pixels == 5 * n
    dirs, rgb, depth, owner = store.gather(torch.arange(store.n_pixels))
    assert owner.tolist() == [i for i in range(5) for _ in range(n)]
    k = frames[0].intrinsics
    # a pixel's direction is its pinhole ray (z = 1); colour and depth are the image's there
    u, v = _pixels(dirs, k)
    assert torch.all(dirs[:, 2] == 1.0)
    for i, frame in enumerate(frames):
        sel = owner == i
        np.testing.assert_array_equal(rgb[sel].numpy(), frame.rgb[v[sel], u[sel]] / np.float32(255.0))
        # depth is kept as float16: within half a unit in the last place (2^-11 relative)
        np.testing.assert_allclose(depth[sel].numpy(), frame.depth_m[v[sel], u[sel]], rtol=2.0**-11)
    # a keyframe's pixels are drawn without replacement
    assert len(set(zip(u[owner == 0].tolist(), v[owner == 0].tolist()))) == n


def test_draw_from_keyframes_covers_exactly_their_pixels_uniformly():
    store, _ = _textured_store(6)
    n = store[0].n_pixels
    gen = torch.Generator().manual_seed(0)
    idx = store.draw(30_000, gen, [1, 4])
    owner = store.gather(idx)[3]
    assert set(owner.tolist()) == {1, 4}
    # every pixel of the two keyframes, and only those, with equal chances (30000 / 96 = 312.5 each)
    expected = set(range(store[1].start, store[1].start + n)) | set(range(store[4].start, store[4].start + n))
    counts = np.bincount(idx.numpy(), minlength=store.n_pixels)
    assert set(np.flatnonzero(counts).tolist()) == expected
    assert counts[sorted(expected)].min() > 312.5 - 5 * np.sqrt(312.5)
    assert store.draw(10, gen, []).numel() == 0
    assert store.draw(10, gen).max() < store.n_pixels


def test_store_grows_by_its_pixels_and_not_by_copies():
    from neb_slam_core.mapping.keyframes import BYTES_PER_PIXEL, GROWTH, ORDER_BYTES_PER_PIXEL

    store, _ = _textured_store(40)
    pixel_bytes = BYTES_PER_PIXEL * store.n_pixels
    order_bytes = ORDER_BYTES_PER_PIXEL * 16 * 12  # one image size: one pixel order
    # the buffers are never more than GROWTH times what they hold; the rest is per-keyframe records
    assert pixel_bytes + order_bytes <= store.nbytes() <= GROWTH * pixel_bytes + order_bytes + 40 * 200


def test_every_pixel_is_kept_with_the_same_chance():
    # 400 keyframes keeping a quarter of 192 pixels: each pixel is kept by Binomial(400, 1/4) of them,
    # mean 100 and standard deviation 8.66
    store, _ = _textured_store(400)
    k = store[0].intrinsics
    dirs, _, _, _ = store.gather(torch.arange(store.n_pixels))
    u, v = _pixels(dirs, k)
    kept = np.bincount((v * 16 + u).numpy(), minlength=16 * 12)
    assert kept.sum() == 400 * 48
    assert kept.min() > 100 - 5 * 8.66 and kept.max() < 100 + 5 * 8.66
    # keyframes do not all keep the same pixels: 400 offsets drawn from 192 give 192 (1 - (191/192)^400)
    # = 168 distinct ones on average
    assert len({kf.order_offset for kf in store.keyframes}) > 150


def test_keyframes_of_two_image_sizes_keep_their_own_pixels():
    rng = np.random.default_rng(2)
    store, frames = KeyframeStore(0.5, seed=1), []
    for i, (h, w) in enumerate([(12, 16), (6, 8), (12, 16), (6, 8)]):
        k = Intrinsics(10.0, 11.0, (w - 1) / 2, (h - 1) / 2, w, h)
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        frames.append(RgbdFrame(rgb, rng.uniform(0.5, 4.0, (h, w)).astype(np.float32), k, i))
        store.add(frames[-1], np.eye(4), i)
    assert [kf.n_pixels for kf in store.keyframes] == [96, 24, 96, 24]
    dirs, rgb, _, owner = store.gather(torch.arange(store.n_pixels))
    for i, frame in enumerate(frames):
        k, sel = frame.intrinsics, owner == i
        u, v = _pixels(dirs[sel], k)
        assert u.min() >= 0 and u.max() < k.width and v.min() >= 0 and v.max() < k.height
        assert len(set(zip(u.tolist(), v.tolist()))) == store[i].n_pixels  # no pixel twice
        np.testing.assert_array_equal(rgb[sel].numpy(), frame.rgb[v, u] / np.float32(255.0))
