import subprocess
import sys

import numpy as np
import pytest
import torch

from neb_slam_core.config import BlockConfig, HashGridConfig, RenderConfig
from neb_slam_core.errors import DatasetError
from neb_slam_core.render.images import render_depth_image
from neb_slam_core.scene.block_map import BlockMap
from neb_slam_core.scene.persistence import load_map, save_map
from neb_slam_core.types import Intrinsics, RgbdFrame

GRID = HashGridConfig(
    n_levels=4, n_features_per_level=2, log2_hashmap_size=12, base_resolution=4, max_resolution=32, init_scale=0.5
)

RENDER_SNIPPET = """
import sys, numpy as np, torch
from neb_slam_core.config import RenderConfig
from neb_slam_core.render.images import render_depth_image
from neb_slam_core.scene.persistence import load_map
from neb_slam_core.types import Intrinsics, RgbdFrame
torch.set_num_threads(int(sys.argv[3]))  # the parent's count: same summation order, same bits
m, extra = load_map(sys.argv[1])
k = Intrinsics(20.0, 20.0, 8.0, 6.0, 16, 12)
frame = RgbdFrame(np.zeros((12, 16, 3), np.uint8), np.full((12, 16), 2.0, np.float32), k, 0)
d, c = render_depth_image(m, frame, np.eye(4), RenderConfig())
np.savez(sys.argv[2], depth=d, rgb=c, note=extra["note"])
"""


def small_map() -> BlockMap:
    m = BlockMap(BlockConfig(edge_m=5.0, grid=GRID), seed=7)
    m.add_block([0.0, 0.0, 2.0])
    m.add_block([2.0, 0.5, 3.0])
    with torch.no_grad():  # make the decoders non-trivial
        for p in m.decoders.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return m


def test_save_and_load_in_a_fresh_process_renders_the_same(tmp_path):
    m = small_map()
    k = Intrinsics(20.0, 20.0, 8.0, 6.0, 16, 12)
    frame = RgbdFrame(np.zeros((12, 16, 3), np.uint8), np.full((12, 16), 2.0, np.float32), k, 0)
    depth, rgb = render_depth_image(m, frame, np.eye(4), RenderConfig())
    assert depth.std() > 0  # a non-trivial image
    path = save_map(m, tmp_path / "map.pt", extra={"note": "hello"}, block_keyframes={1: [4, 9]})
    out = tmp_path / "render.npz"
    subprocess.run(
        [sys.executable, "-c", RENDER_SNIPPET, str(path), str(out), str(torch.get_num_threads())], check=True
    )
    loaded = np.load(out)
    assert np.array_equal(loaded["depth"], depth)
    assert np.array_equal(loaded["rgb"], rgb)
    assert str(loaded["note"]) == "hello"
    m2, _ = load_map(path)
    for (name, a), (_, b) in zip(m.state_dict().items(), m2.state_dict().items()):
        assert torch.equal(a, b), name
    assert len(m2) == 2
    # the blocks' keyframes are stored as format version 1 has them, one list per block
    payload = torch.load(path, weights_only=True)
    assert [b["keyframe_ids"] for b in payload["blocks"]] == [[], [4, 9]]
    assert m2.block_cfg == m.block_cfg


def test_load_rejects_other_files(tmp_path):
    bad = tmp_path / "x.pt"
    torch.save({"format": "something else"}, bad)
    with pytest.raises(DatasetError, match="x.pt.*not a NeB-SLAM map"):
        load_map(bad)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file")
    with pytest.raises(DatasetError, match="junk.pt"):
        load_map(junk)
    with pytest.raises(DatasetError, match="not found"):
        load_map(tmp_path / "missing.pt")
    m = small_map()
    p = save_map(m, tmp_path / "v.pt")
    payload = torch.load(p, weights_only=True)
    payload["version"] = 99
    torch.save(payload, p)
    with pytest.raises(DatasetError, match="version 99"):
        load_map(p)


def test_the_observed_space_record_is_saved_and_a_map_without_it_counts_as_observed(tmp_path):
    m = small_map()
    k = Intrinsics(20.0, 20.0, 8.0, 6.0, 16, 12)
    assert m.mark_observed(np.full((12, 16), 2.0, np.float32), k, np.eye(4), 0.1) == {0, 1}
    seen = [b.observed.clone() for b in m.blocks]
    assert 0 < int(seen[0].sum()) < seen[0].numel()
    p = save_map(m, tmp_path / "map.pt")
    m2, _ = load_map(p)
    assert all(torch.equal(a, b.observed) for a, b in zip(seen, m2.blocks, strict=True))
    payload = torch.load(p, weights_only=True)
    for entry in payload["blocks"]:
        del entry["observed"]
    torch.save(payload, p)
    m3, _ = load_map(p)
    assert all(bool(b.observed.all()) for b in m3.blocks)
