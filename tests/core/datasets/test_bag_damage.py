"""Damaged ROS 2 bags (neb_slam_core.io.bag_salvage through the bag loader): storage files cut short as
by a crash, a missing metadata.yaml, and damage that is not read around.

The bags are made by the repository's own converter from a tiny synthetic scene and cut with plain
file truncation; what is read back is compared with the frames of the intact bag.
"""

from __future__ import annotations

import logging
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

from neb_slam_core.cli.main import main
from neb_slam_core.datasets import open_dataset
from neb_slam_core.datasets.bag import BagDataset
from neb_slam_core.errors import DatasetError
from neb_slam_core.io.bag import IMAGE_TYPE, decode_rgb, rgb_to_msg, ros2_typestore
from neb_slam_core.io.bag_salvage import salvage_bag

N_FRAMES = 12
STORAGE_SUFFIX = {"mcap": ".mcap", "sqlite3": ".db3"}


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene") / "tiny"
    assert main(["synth", str(out), "--preset", "small", "--frames", str(N_FRAMES)]) == 0
    return out


@pytest.fixture(scope="module", params=["mcap", "sqlite3"])
def intact_bag(request, tiny_scene, tmp_path_factory) -> tuple[Path, str]:
    bag = tmp_path_factory.mktemp(request.param) / "bag"
    assert main(["convert", "tum", str(tiny_scene), str(bag), "--storage", request.param]) == 0
    return bag, request.param


def damaged_copy(bag: Path, dest: Path, fraction: float) -> tuple[Path, Path]:
    """A copy of ``bag`` whose storage file is cut to ``fraction`` of its size -> (bag, storage file)."""
    shutil.copytree(bag, dest)
    (storage,) = [p for p in dest.iterdir() if p.suffix in (".mcap", ".db3")]
    os.truncate(storage, int(storage.stat().st_size * fraction))
    return dest, storage


def damage_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "rosbags cannot open it" in r.getMessage()]


def assert_same_frames(got, want, n: int) -> None:
    for i in range(n):
        g, w = got[i], want[i]
        assert g.stamp_ns == w.stamp_ns
        np.testing.assert_array_equal(g.rgb, w.rgb)
        np.testing.assert_array_equal(g.depth_m, w.depth_m)
        np.testing.assert_array_equal(g.T_world_cam, w.T_world_cam)
        assert g.intrinsics == w.intrinsics


def test_truncated_bag_gives_its_first_frames_and_warns_once(intact_bag, tmp_path, caplog, capsys):
    bag, storage_kind = intact_bag
    damaged, storage = damaged_copy(bag, tmp_path / "cut", 1 / 2)
    caplog.set_level(logging.WARNING)
    assert main(["info", str(damaged)]) == 0
    out = capsys.readouterr().out
    (warning,) = damage_warnings(caplog)
    assert str(damaged) in warning and storage.name in warning
    assert "lost per metadata.yaml: /camera/depth/image" in warning  # what was lost, from the counts
    n = int(next(ln for ln in out.splitlines() if ln.startswith("frames:")).split()[1])
    assert 2 <= n < N_FRAMES, out

    caplog.clear()
    ds = BagDataset(damaged)
    assert len(damage_warnings(caplog)) == 1 and len(ds) == n
    assert_same_frames(ds, BagDataset(bag), n)
    # a pickled copy (a worker process) reads from its own handles without indexing again
    caplog.clear()
    copy = pickle.loads(pickle.dumps(ds))
    assert_same_frames(copy, ds, n)
    assert not damage_warnings(caplog)
    ds.close()
    assert ds[n - 1].stamp_ns == copy[n - 1].stamp_ns  # reopened after close


def test_bag_without_metadata_yaml_is_read(intact_bag, tmp_path, caplog):
    bag, _ = intact_bag
    whole = tmp_path / "no_metadata"
    shutil.copytree(bag, whole)
    (whole / "metadata.yaml").unlink()
    caplog.set_level(logging.WARNING)
    ds = open_dataset(whole)  # still detected as a bag
    assert ds.name == "bag" and len(ds) == N_FRAMES
    assert_same_frames(ds, BagDataset(bag), N_FRAMES)
    (warning,) = damage_warnings(caplog)
    assert "metadata.yaml missing" in warning and f"{4 * N_FRAMES} messages read" in warning

    caplog.clear()
    cut, _ = damaged_copy(whole, tmp_path / "no_metadata_cut", 1 / 2)
    ds = BagDataset(cut)
    assert 2 <= len(ds) < N_FRAMES
    (warning,) = damage_warnings(caplog)
    assert "how many were lost is unknown" in warning


def test_single_truncated_storage_file_is_read(intact_bag, tmp_path, caplog):
    bag, _ = intact_bag
    _, storage = damaged_copy(bag, tmp_path / "cut", 1 / 2)
    caplog.set_level(logging.WARNING)
    ds = BagDataset(storage)
    assert 2 <= len(ds) < N_FRAMES
    assert len(damage_warnings(caplog)) == 1


def test_bag_cut_before_any_message_is_an_error_naming_it(intact_bag, tmp_path):
    bag, storage_kind = intact_bag
    damaged, storage = damaged_copy(bag, tmp_path / "short", 1.0)
    os.truncate(storage, 40)  # the file's first bytes only
    # one line naming the file: nothing readable (mcap), or not even the topics table (sqlite3)
    expected = "no readable message" if storage_kind == "mcap" else "cannot read the bag's topics table"
    with pytest.raises(DatasetError, match=expected) as err:
        BagDataset(damaged)
    assert str(damaged) in str(err.value) and storage.name in str(err.value) and "\n" not in str(err.value)


def test_other_damage_is_still_an_error(intact_bag, tmp_path):
    bag, _ = intact_bag
    broken = tmp_path / "broken"
    shutil.copytree(bag, broken)
    (storage,) = [p for p in broken.iterdir() if p.suffix in (".mcap", ".db3")]
    data = bytearray(storage.read_bytes())
    data[:16] = b"\0" * 16  # the file's magic, not its length
    storage.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"cannot open bag") as err:
        BagDataset(broken)
    assert str(broken) in str(err.value)


def test_compressed_mcap_keeps_its_whole_chunks(tmp_path):
    # zstd chunks of 1 MiB (rosbags' writer); a cut through one loses that chunk whole
    ts = ros2_typestore()
    path = tmp_path / "zstd"
    writer = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    rng = np.random.default_rng(0)
    stamps = [1_000_000_000 + k * 33_000_000 for k in range(12)]
    images = [rng.integers(0, 256, (288, 384, 3), dtype=np.uint8) for _ in stamps]  # incompressible
    with writer:
        conn = writer.add_connection("/camera/rgb/image", IMAGE_TYPE, typestore=ts)
        for stamp, rgb in zip(stamps, images):
            writer.write(conn, stamp, ts.serialize_cdr(rgb_to_msg(ts, rgb, stamp, "cam"), IMAGE_TYPE))
    storage = path / "zstd.mcap"
    os.truncate(storage, int(storage.stat().st_size * 0.6))
    salvaged = salvage_bag(path)
    assert "compressed chunk is cut short (lost whole)" in salvaged.report
    (conn,) = salvaged.connections
    got = list(salvaged.messages([conn]))
    assert 0 < len(got) < len(stamps) and [log_ns for _, log_ns, _ in got] == stamps[: len(got)]
    for (_, _, raw), rgb in zip(got, images):
        np.testing.assert_array_equal(decode_rgb(salvaged.deserialize(raw, IMAGE_TYPE)), rgb)
