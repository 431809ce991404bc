"""The map update byte layout: round trip, exact reproduction of the sender's map, and clear errors."""

import struct

import numpy as np
import pytest
import torch

from neb_slam_core.config import BlockConfig, HashGridConfig
from neb_slam_core.scene import map_update
from neb_slam_core.scene.block_map import BlockMap
from neb_slam_core.scene.map_update import MapUpdateError

SMALL_GRID = HashGridConfig(
    n_levels=2, n_features_per_level=2, log2_hashmap_size=4, base_resolution=2, max_resolution=4, init_scale=0.1
)


def make_map(seed: int = 3, observed_voxel_m: float = 0.5) -> BlockMap:
    cfg = BlockConfig(edge_m=5.0, grid=SMALL_GRID, observed_voxel_m=observed_voxel_m)
    return BlockMap(cfg, grid_backend="reference", seed=seed)


def trained(seed: int = 3, observed_voxel_m: float = 0.5) -> BlockMap:
    """A sender's map with three blocks whose tables, observed-space records (10^3 voxels each) and
    decoders differ from their initial values."""
    m = make_map(seed, observed_voxel_m)
    for c in ([0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [4.0, 4.0, -1.0]):
        m.add_block(c)
    g = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for b in m.blocks:
            b.grid.table.copy_(torch.rand(b.grid.table.shape, generator=g))
            b.observed.copy_(torch.rand(b.observed.shape, generator=g) < 0.3)
        for p in m.decoders.parameters():
            p.copy_(torch.rand(p.shape, generator=g))
    return m


def test_layout_sizes_are_the_documented_ones():
    m = trained()
    poses = np.stack([np.eye(4)] * 2)
    data = map_update.encode(
        map_update.capture(
            m, [2, 0], version=5, ack_stamp_ns=123, keyframe_stamps_ns=[10, 20], keyframe_poses=poses, loop_stamp_ns=77
        )
    )
    table_numel = m.blocks[0].grid.table.numel()
    n_decoder = sum(p.numel() for p in m.decoders.parameters())
    record = 125  # 10^3 voxels, 8 a byte
    assert len(data) == 84 + 2 * (16 + 4 * table_numel + record) + 4 * n_decoder + 2 * 8 + 2 * 128
    assert data[:4] == b"NEBU"
    assert struct.unpack_from("<HHQq", data, 4) == (5, 0, 5, 123)
    width = m.blocks[0].grid.table.shape[-1]
    assert struct.unpack_from("<IIIIIqIQiIHHIf", data, 24) == (
        2,
        table_numel,
        n_decoder,
        2,
        84,
        77,
        record,
        0,
        -1,
        0,
        width,
        4,
        0,
        0.0,
    )
    # the first block record is block 0 (ids are sorted), its centre follows its id, its record its table
    assert struct.unpack_from("<I3f", data, 84) == (0, 0.0, 0.0, 0.0)
    first = data[84 + 16 + 4 * table_numel :][:record]
    bits = np.unpackbits(np.frombuffer(first, np.uint8), bitorder="little").astype(bool)
    assert np.array_equal(bits, m.blocks[0].observed.numpy().reshape(-1))
    assert map_update.decode(data).loop_stamp_ns == 77


@pytest.mark.parametrize("header_bytes", [44, 52])
def test_a_format_1_update_still_reads(header_bytes):
    """Format 1 had no observed-space records, and its first updates no loop stamp: header_bytes tells a
    reader where the blocks start, so both decode (loop stamp -1 without it; no record, which leaves the
    receiver's own record as it was)."""
    m = trained(observed_voxel_m=0.0)  # no record: the blocks are laid out as format 1 lays them out
    data = map_update.encode(map_update.capture(m, [1], 3, 9, [5], np.eye(4)[None], loop_stamp_ns=123))
    old = bytearray(data[:header_bytes] + data[84:])
    struct.pack_into("<H", old, 4, 1)
    struct.pack_into("<I", old, 40, header_bytes)
    u = map_update.decode(bytes(old))
    loop = -1 if header_bytes == 44 else 123
    assert (u.version, u.ack_stamp_ns, u.block_ids, u.loop_stamp_ns) == (3, 9, [1], loop)
    np.testing.assert_array_equal(u.blocks[0].table, map_update.decode(data).blocks[0].table)
    receiver = make_map()
    receiver.add_block([0.0, 0.0, 0.0])
    receiver.blocks[0].observed.fill_(True)
    map_update.apply(u, receiver)
    assert receiver.blocks[0].observed.all() and not receiver.blocks[1].observed.any()


def test_the_senders_epoch_and_durable_keyframes_round_trip_and_a_format_2_update_reads_without_them():
    m = trained()
    update = map_update.capture(m, [0], 4, 9, [5], np.eye(4)[None])
    update.epoch, update.durable_keyframes = 2**63 + 5, 17
    data = map_update.encode(update)
    u = map_update.decode(data)
    assert (u.epoch, u.durable_keyframes, u.version) == (2**63 + 5, 17, 4)
    old = bytearray(data[:56] + data[84:])  # format 2: the header ends after observed_bytes
    struct.pack_into("<H", old, 4, 2)
    struct.pack_into("<I", old, 40, 56)
    u2 = map_update.decode(bytes(old))
    assert (u2.epoch, u2.durable_keyframes, u2.version, u2.block_ids) == (0, -1, 4, [0])
    np.testing.assert_array_equal(u2.blocks[0].table, u.blocks[0].table)


def test_applying_updates_reproduces_the_senders_map_exactly():
    sender = trained()
    poses = np.stack([np.eye(4), np.diag([1.0, -1.0, -1.0, 1.0])])
    poses[1, :3, 3] = [0.1234567891234, -2.0, 3.5]
    receiver = make_map(seed=99)  # different initial decoders: the update must overwrite them all
    receiver.add_block([0.0, 0.0, 0.0])
    update = map_update.decode(map_update.encode(map_update.capture(sender, [1, 2], 2, 555, [7, 9], poses)))
    assert update.version == 2 and update.ack_stamp_ns == 555 and update.block_ids == [1, 2]
    assert map_update.apply(update, receiver) == [1, 2]
    np.testing.assert_array_equal(update.keyframe_poses, poses)  # float64, bit-exact
    assert update.keyframe_stamps_ns.tolist() == [7, 9]
    for i in (1, 2):
        assert torch.equal(receiver.blocks[i].grid.table, sender.blocks[i].grid.table)
        assert torch.equal(receiver.blocks[i].centre, sender.blocks[i].centre)
        assert torch.equal(receiver.blocks[i].observed, sender.blocks[i].observed)
    for a, b in zip(receiver.decoders.parameters(), sender.decoders.parameters()):
        assert torch.equal(a, b)
    # block 0 was not in the update: the receiver's own table is untouched
    assert not torch.equal(receiver.blocks[0].grid.table, sender.blocks[0].grid.table)
    pts = torch.tensor([[4.5, 0.2, -0.3], [4.0, 4.0, -1.0]])
    assert torch.equal(receiver.query(pts, [1, 2]).sdf, sender.query(pts, [1, 2]).sdf)


def test_decode_accepts_the_buffer_types_of_ros_messages():
    import array

    data = map_update.encode(map_update.capture(trained(), [0], 1, -1, [], np.zeros((0, 4, 4))))
    for buf in (bytearray(data), array.array("B", data), memoryview(data)):
        u = map_update.decode(buf)
        assert u.block_ids == [0] and len(u.keyframe_poses) == 0 and u.ack_stamp_ns == -1


def test_bad_updates_are_refused_with_what_is_wrong():
    sender = trained()
    data = map_update.encode(map_update.capture(sender, [0, 1, 2], 1, 0, [], np.zeros((0, 4, 4))))
    with pytest.raises(MapUpdateError, match="magic"):
        map_update.decode(b"XXXX" + data[4:])
    with pytest.raises(MapUpdateError, match="header announces"):
        map_update.decode(data[:-4])
    with pytest.raises(MapUpdateError, match="shorter than"):
        map_update.decode(data[:10])
    with pytest.raises(MapUpdateError, match="format 9"):
        map_update.decode(data[:4] + struct.pack("<H", 9) + data[6:])
    with pytest.raises(MapUpdateError, match="header_bytes 12"):
        map_update.decode(data[:40] + struct.pack("<I", 12) + data[44:])
    # a receiver with no blocks cannot take block 1 before block 0 (a lost update)
    only_later = map_update.decode(map_update.encode(map_update.capture(sender, [1], 1, 0, [], np.zeros((0, 4, 4)))))
    with pytest.raises(MapUpdateError, match="an update was lost"):
        map_update.apply(only_later, make_map())
    # a receiver whose block 0 sits elsewhere has diverged from the sender
    other = make_map()
    other.add_block([1.0, 0.0, 0.0])
    with pytest.raises(MapUpdateError, match="diverged"):
        map_update.apply(map_update.decode(data), other)
    # a receiver with another grid size
    finer = BlockMap(
        BlockConfig(
            edge_m=5.0, grid=HashGridConfig(n_levels=2, log2_hashmap_size=6, base_resolution=2, max_resolution=4)
        ),
        grid_backend="reference",
        seed=3,
    )
    with pytest.raises(MapUpdateError, match="grid config"):
        map_update.apply(map_update.decode(data), finer)
    wider = BlockMap(
        BlockConfig(
            edge_m=5.0, grid=HashGridConfig(n_levels=3, log2_hashmap_size=4, base_resolution=2, max_resolution=4)
        ),
        grid_backend="reference",
    )
    with pytest.raises(MapUpdateError, match="decoder config"):
        map_update.apply(map_update.decode(data), wider)
    # a receiver with another observed-space voxel
    coarser = make_map(observed_voxel_m=1.0)
    with pytest.raises(MapUpdateError, match="125-byte observed-space record.*125 voxels"):
        map_update.apply(map_update.decode(data), coarser)


def _rows(block) -> torch.Tensor:
    return block.grid.table.view(-1, block.grid.table.shape[-1])


def test_after_a_blocks_first_update_only_its_changed_rows_go_and_the_receiver_matches_exactly():
    sender, receiver = trained(), make_map(seed=99)
    mirror = map_update.ReceiverMirror()
    first = map_update.capture(sender, [0, 1, 2], 1, 0, [], np.zeros((0, 4, 4)), mirror=mirror)
    assert all(b.rows is None for b in first.blocks)  # a block's first update is whole
    map_update.apply(map_update.decode(map_update.encode(first)), receiver)
    with torch.no_grad():
        _rows(sender.blocks[1])[[3, 7]] += 0.25
    update = map_update.capture(sender, [0, 1], 2, 0, [], np.zeros((0, 4, 4)), mirror=mirror)
    data = map_update.encode(update)
    width = sender.blocks[0].grid.table.shape[-1]
    record = 125
    n_decoder = sum(p.numel() for p in sender.decoders.parameters())
    # block 0 unchanged: no rows; block 1: rows 3 and 7, each an index and its values
    assert len(data) == 84 + 2 * (16 + 4 + record) + 2 * (4 + 4 * width) + 4 * n_decoder
    assert struct.unpack_from("<IHH", data, 68) == (2, width, 4)
    decoded = map_update.decode(data)
    assert [b.rows.tolist() for b in decoded.blocks] == [[], [3, 7]]
    map_update.apply(decoded, receiver)
    for a, b in zip(receiver.blocks, sender.blocks):
        assert torch.equal(a.grid.table, b.grid.table) and torch.equal(a.observed, b.observed)


def test_float16_and_a_tolerance_keep_every_receiver_value_within_their_bound():
    """float16 rounds a value v by at most |v| 2^-11 (half its 10-bit mantissa's step; the tables here hold
    normal numbers); a row whose values moved by at most the tolerance stays as the receiver has it."""
    tol = 1e-3
    sender, receiver = trained(), make_map(seed=99)
    mirror = map_update.ReceiverMirror(tolerance=tol, float16=True)
    map_update.apply(
        map_update.decode(map_update.encode(map_update.capture(sender, [0], 1, 0, [], [], mirror=mirror))), receiver
    )
    table = _rows(sender.blocks[0])
    with torch.no_grad():
        table += 0.5 * tol  # every row moves, by half the tolerance
        table[5] += 0.01  # one row by more
    update = map_update.capture(sender, [0], 2, 0, [], [], mirror=mirror)
    data = map_update.encode(update)
    assert update.value_bytes == 2 and update.blocks[0].rows.tolist() == [5]
    map_update.apply(map_update.decode(data), receiver)
    got, want = _rows(receiver.blocks[0]), table
    assert torch.equal(got[5], want[5].half().float())
    bound = tol + want.abs() * 2.0**-11
    assert bool(((got - want).abs() <= bound).all())
    # measured against what the receiver has (row 5 rounded to float16), nothing is left to send
    assert map_update.capture(sender, [0], 3, 0, [], [], mirror=mirror).blocks[0].rows.tolist() == []


def test_a_format_3_update_still_reads_and_a_partial_new_block_is_refused():
    m = trained()
    data = map_update.encode(map_update.capture(m, [0], 4, 9, [5], np.eye(4)[None]))
    old = bytearray(data[:68] + data[84:])  # format 3: no row fields, float32 tables
    struct.pack_into("<H", old, 4, 3)
    struct.pack_into("<I", old, 40, 68)
    u = map_update.decode(bytes(old))
    assert (u.version, u.block_ids, u.value_bytes, u.blocks[0].rows) == (4, [0], 4, None)
    np.testing.assert_array_equal(u.blocks[0].table, map_update.decode(data).blocks[0].table)
    mirror = map_update.ReceiverMirror()
    map_update.capture(m, [0], 1, 0, [], [], mirror=mirror)
    partial = map_update.decode(map_update.encode(map_update.capture(m, [0], 2, 0, [], [], mirror=mirror)))
    with pytest.raises(MapUpdateError, match="new block 0 in part"):
        map_update.apply(partial, make_map())


def test_a_format_4_update_with_rows_still_reads():
    sender, mirror = trained(), map_update.ReceiverMirror()
    map_update.capture(sender, [0, 1], 1, 0, [], [], mirror=mirror)
    with torch.no_grad():
        _rows(sender.blocks[1])[[2]] += 0.5
    data = map_update.encode(map_update.capture(sender, [0, 1], 2, 0, [], [], mirror=mirror))
    old = bytearray(data[:76] + data[84:])  # format 4: no delta fields
    struct.pack_into("<H", old, 4, 4)
    struct.pack_into("<I", old, 40, 76)
    u = map_update.decode(bytes(old))
    assert [b.rows.tolist() for b in u.blocks] == [[], [2]] and u.delta_step == 0.0
    np.testing.assert_array_equal(u.blocks[1].table, map_update.decode(data).blocks[1].table)


STEP = 2.0**-10


def _delta_pair():
    """A sender, a receiver that applied the sender's first (whole, float16) update, and the mirror."""
    sender, receiver = trained(), make_map(seed=99)
    mirror = map_update.ReceiverMirror(float16=True, delta_step=STEP)
    first = map_update.capture(sender, [0, 1, 2], 1, 0, [], [], mirror=mirror)
    assert all(b.whole for b in first.blocks) and first.value_bytes == 2
    map_update.apply(map_update.decode(map_update.encode(first)), receiver)
    return sender, receiver, mirror


def test_changes_in_steps_are_the_hand_worked_counts_and_leave_the_receiver_with_the_mirrors_tables():
    sender, receiver, mirror = _delta_pair()
    # what the receivers hold: the first update's float16 values (within 2^-12 of the values in [0, 1))
    held = _rows(sender.blocks[1]).detach().half().float().numpy()
    with torch.no_grad():
        _rows(sender.blocks[1])[3] += 3 * STEP  # three steps
        _rows(sender.blocks[2])[4, 0] -= 200 * STEP  # beyond one byte's 127 steps
    update = map_update.capture(sender, [0, 1, 2], 2, 0, [], [], mirror=mirror)
    data = map_update.encode(update)
    assert struct.unpack_from("<IHHIf", data, 68)[3:] == (3, STEP)  # three blocks as changes, the step
    decoded = map_update.decode(data)
    # float16's rounding (at most a quarter step here) is in no change: rounded to whole steps, 0 for every
    # value but those moved
    steps = decoded.blocks[1].steps.reshape(-1, 2)
    want = np.zeros_like(steps)
    want[3] = 3
    assert steps.dtype == np.int8 and np.array_equal(steps, want)
    table = _rows(sender.blocks[1]).detach().numpy()
    assert np.array_equal(steps, np.rint((table - held) / STEP))
    assert not decoded.blocks[0].steps.any()  # block 0 did not move
    far = decoded.blocks[2].steps.reshape(-1, 2)  # block 2 needs two bytes a value
    assert far.dtype == np.int16 and far[4, 0] == -200 and np.count_nonzero(far) == 1
    # block records: head, step_bytes and packed size, the zlib stream, the record (block 0, 1, then 2)
    at = 84
    for block, width in ((0, 1), (1, 1), (2, 2)):
        assert struct.unpack_from("<I", data, at)[0] == block
        got_width, packed = struct.unpack_from("<BI", data, at + 16)
        assert got_width == width and packed < 64 * width  # mostly zeros: zlib packs them
        at += 16 + 5 + packed + 125
    map_update.apply(decoded, receiver)
    for i in (0, 1, 2):
        assert torch.equal(_rows(receiver.blocks[i]), torch.from_numpy(mirror._tables[i]))
        diff = (receiver.blocks[i].grid.table - sender.blocks[i].grid.table).detach().abs()
        assert float(diff.max()) <= STEP / 2


def test_changes_in_steps_track_a_randomly_moving_map_within_half_a_step():
    sender, receiver, mirror = _delta_pair()
    g = torch.Generator().manual_seed(11)
    for version in range(2, 8):
        with torch.no_grad():
            for b in sender.blocks:  # Adam-like steps: every value moves a little
                b.grid.table.add_(0.02 * torch.randn(b.grid.table.shape, generator=g))
        data = map_update.encode(map_update.capture(sender, [0, 1, 2], version, 0, [], [], mirror=mirror))
        map_update.apply(map_update.decode(data), receiver)
        for a, b in zip(receiver.blocks, sender.blocks):
            assert float((a.grid.table - b.grid.table).detach().abs().max()) <= STEP / 2 + 1e-6
        assert all(torch.equal(_rows(receiver.blocks[i]), torch.from_numpy(mirror._tables[i])) for i in range(3))


def test_bad_changes_in_steps_are_refused():
    with pytest.raises(ValueError, match="power of two"):
        map_update.ReceiverMirror(delta_step=0.003)
    sender, receiver, mirror = _delta_pair()
    data = bytearray(map_update.encode(map_update.capture(sender, [0], 2, 0, [], [], mirror=mirror)))
    bad_step = bytearray(data)
    struct.pack_into("<f", bad_step, 80, 0.003)
    with pytest.raises(MapUpdateError, match="delta_step 0.003"):
        map_update.decode(bytes(bad_step))
    packed = struct.unpack_from("<I", data, 84 + 16)[0]
    broken = bytearray(data)
    broken[84 + 20 : 84 + 20 + packed] = bytes(packed)  # zeros are no zlib stream
    with pytest.raises(MapUpdateError, match="block 0: its changes do not inflate"):
        map_update.decode(bytes(broken))
    # a receiver that never got block 0 whole cannot take its changes
    with pytest.raises(MapUpdateError, match="new block 0 as changes"):
        map_update.apply(map_update.decode(bytes(data)), make_map())
