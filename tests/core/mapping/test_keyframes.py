"""The keyframe store's block index: which keyframes belong to which block."""

from __future__ import annotations

import numpy as np

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
