"""The map update: the part of a block map that a mapping step changed, as one versioned byte string.

The mapper sends it (ROS topic ``map_update``, std_msgs/UInt8MultiArray) to trackers that hold a copy of
the map: the hash tables and observed-space records of the blocks it changed, all decoder parameters,
and the current poses of all keyframes (mapping refines them). Applying every update in order reproduces
the mapper's map exactly (float32 tables and decoders, float64 poses: no rounding on the way); a
receiver's observed-space record becomes the union of its own and the mapper's.

A mapper that checkpoints says which of its keyframes a restart would keep (``durable_keyframes``), and
every start of a mapper has its own ``epoch``: a receiver that sees a new epoch knows the sender restarted
(from a checkpoint, with the keyframes the update's poses list), starts counting versions anew and hands it
the keyframes it lacks.

Binary layout, version 3, little-endian, no padding::

    header (68 bytes)
      char[4]  magic            b"NEBU"
      uint16   format           3 (1: without observed_bytes, 2: without epoch and durable_keyframes;
                                both still read)
      uint16   reserved         0
      uint64   version          update counter of the sender, 1, 2, 3, ... (receivers drop old ones)
      int64    ack_stamp_ns     stamp of the newest keyframe the map has integrated (-1: none)
      uint32   n_blocks         B, blocks in this update
      uint32   table_numel      float32 values per block table (L * T * F of the block config)
      uint32   n_decoder        float32 values of all decoder parameters
      uint32   n_keyframes      K
      uint32   header_bytes     68 (readers skip to here: later versions may append fields)
      int64    loop_stamp_ns    stamp of the newest ``loop_closure`` correction the map has handled (-1:
                                none); appended after the first 44 bytes: a 44-byte header reads as -1
      uint32   observed_bytes   bytes of each block's observed-space record (0: none); format 2
      uint64   epoch            the sender's start: a new value after each restart (0: not told); format 3
      int32    durable_keyframes  keyframes 0..n-1 are in the sender's last checkpoint (-1: it writes
                                none); format 3
    B times
      uint32   block_id
      float32  centre_world[3]  metres
      float32  table[table_numel]   the block's hash table, row-major (entries, features)
      uint8    observed[observed_bytes]  the block's (V, V, V) record of observed voxels
                                (:class:`~.block.NeuralBlock`), flattened row-major, 8 voxels a byte,
                                least significant bit first
    float32  decoders[n_decoder]    parameters in ``Decoders.parameters()`` order, each row-major
    int64    keyframe_stamps_ns[K]
    float64  keyframe_poses[K][4][4]   T_world_cam of keyframes 0..K-1, row-major

Block ids are dense (0, 1, 2, ...): a receiver that does not have block ``id`` yet creates it, and it
must then have every lower id already.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import NebSlamError
from .block_map import BlockMap

MAGIC = b"NEBU"
FORMAT_VERSION = 3
READABLE_FORMATS = (1, 2, 3)
_HEADER = struct.Struct("<4sHHQqIIIII")  # the first 44 bytes; header_bytes says where the blocks start
_HEADER_EXTRA = struct.Struct("<qI")  # fields appended since: loop_stamp_ns, observed_bytes (format 2)
_HEADER_RESTART = struct.Struct("<Qi")  # epoch, durable_keyframes (format 3)
_LOOP_STAMP = struct.Struct("<q")
_BLOCK_HEAD = struct.Struct("<I3f")


class MapUpdateError(NebSlamError):
    """A map update is malformed or does not fit the receiving map."""


@dataclass
class BlockState:
    """One block's identity and parameters: ``table`` is float32 ``(table_numel,)``; ``observed`` its
    observed-space record packed 8 voxels a byte (:func:`pack_observed`), empty without one."""

    block_id: int
    centre_world: np.ndarray
    table: np.ndarray
    observed: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))


def pack_observed(observed: torch.Tensor) -> np.ndarray:
    """A block's ``(V, V, V)`` bool record as bytes: row-major, 8 voxels a byte, least significant first."""
    return np.packbits(observed.detach().cpu().numpy().reshape(-1), bitorder="little")


@dataclass
class MapUpdate:
    """A decoded update (see the module docstring for the meaning of each field)."""

    version: int
    ack_stamp_ns: int
    blocks: list[BlockState]
    decoders: np.ndarray
    keyframe_stamps_ns: np.ndarray
    keyframe_poses: np.ndarray
    loop_stamp_ns: int = -1
    epoch: int = 0
    durable_keyframes: int = -1

    @property
    def block_ids(self) -> list[int]:
        return [b.block_id for b in self.blocks]


def capture(
    block_map: BlockMap,
    block_ids,
    version: int,
    ack_stamp_ns: int,
    keyframe_stamps_ns,
    keyframe_poses,
    loop_stamp_ns: int = -1,
) -> MapUpdate:
    """The update carrying blocks ``block_ids`` of ``block_map``, its decoders and the keyframe poses
    ``(K, 4, 4)`` with their stamps ``(K,)``, as copies (another thread or process may apply or encode it
    while the map moves on); ``loop_stamp_ns`` names the newest loop correction in it."""
    stamps = np.array(keyframe_stamps_ns, dtype=np.int64).reshape(-1)
    poses = np.array(keyframe_poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(stamps) != len(poses):
        raise ValueError(f"{len(stamps)} keyframe stamps for {len(poses)} poses")
    blocks = []
    for i in sorted(int(b) for b in block_ids):
        block = block_map.blocks[i]
        blocks.append(
            BlockState(
                i,
                block.centre.detach().cpu().numpy().astype(np.float32),
                block.grid.table.detach().cpu().reshape(-1).numpy().copy(),
                pack_observed(block.observed),
            )
        )
    decoders = torch.nn.utils.parameters_to_vector(block_map.decoders.parameters()).detach().cpu().numpy().copy()
    return MapUpdate(version, ack_stamp_ns, blocks, decoders, stamps, poses, loop_stamp_ns)


def encode(update: MapUpdate) -> bytes:
    """``update`` in the binary layout of the module docstring."""
    table_numel = update.blocks[0].table.size if update.blocks else 0
    observed_bytes = update.blocks[0].observed.size if update.blocks else 0
    for b in update.blocks:
        if b.table.size != table_numel or b.observed.size != observed_bytes:
            raise ValueError(f"block {b.block_id}'s table or record differs in size from the update's first block")
    stamps = np.ascontiguousarray(update.keyframe_stamps_ns, dtype="<i8").reshape(-1)
    poses = np.ascontiguousarray(update.keyframe_poses, dtype="<f8").reshape(-1, 4, 4)
    parts = [
        _HEADER.pack(
            MAGIC,
            FORMAT_VERSION,
            0,
            update.version,
            update.ack_stamp_ns,
            len(update.blocks),
            table_numel,
            update.decoders.size,
            len(stamps),
            _HEADER.size + _HEADER_EXTRA.size + _HEADER_RESTART.size,
        ),
        _HEADER_EXTRA.pack(update.loop_stamp_ns, observed_bytes),
        _HEADER_RESTART.pack(update.epoch, update.durable_keyframes),
    ]
    for b in sorted(update.blocks, key=lambda b: b.block_id):
        parts.append(_BLOCK_HEAD.pack(b.block_id, *map(float, b.centre_world)))
        parts.append(np.asarray(b.table).astype("<f4", copy=False).tobytes())
        parts.append(np.asarray(b.observed, dtype=np.uint8).tobytes())
    parts += [np.asarray(update.decoders).astype("<f4", copy=False).tobytes(), stamps.tobytes(), poses.tobytes()]
    return b"".join(parts)


def decode(data) -> MapUpdate:
    """Parse an update (bytes, bytearray, memoryview or array of uint8); the arrays view ``data``."""
    buf = memoryview(data).cast("B")
    if len(buf) < _HEADER.size:
        raise MapUpdateError(f"map update of {len(buf)} bytes is shorter than its {_HEADER.size}-byte header")
    magic, fmt, _, version, ack, n_blocks, table_numel, n_decoder, n_kf, header_bytes = _HEADER.unpack_from(buf)
    if magic != MAGIC:
        raise MapUpdateError(f"not a map update: magic {bytes(magic)!r}, expected {MAGIC!r}")
    if fmt not in READABLE_FORMATS:
        raise MapUpdateError(f"map update format {fmt} is not supported (this software reads {READABLE_FORMATS})")
    if header_bytes < _HEADER.size or header_bytes > len(buf):
        raise MapUpdateError(f"map update header_bytes {header_bytes} is outside {_HEADER.size}..{len(buf)}")
    loop_stamp, observed_bytes, epoch, durable = -1, 0, 0, -1
    if fmt >= 2 and header_bytes >= _HEADER.size + _HEADER_EXTRA.size:
        loop_stamp, observed_bytes = _HEADER_EXTRA.unpack_from(buf, _HEADER.size)
        if fmt >= 3 and header_bytes >= _HEADER.size + _HEADER_EXTRA.size + _HEADER_RESTART.size:
            epoch, durable = _HEADER_RESTART.unpack_from(buf, _HEADER.size + _HEADER_EXTRA.size)
    elif header_bytes >= _HEADER.size + _LOOP_STAMP.size:
        (loop_stamp,) = _LOOP_STAMP.unpack_from(buf, _HEADER.size)
    block_bytes = _BLOCK_HEAD.size + 4 * table_numel + observed_bytes
    expected = header_bytes + n_blocks * block_bytes + 4 * n_decoder + 8 * n_kf + 128 * n_kf
    if len(buf) != expected:
        raise MapUpdateError(
            f"map update of {len(buf)} bytes, its header announces {expected} "
            f"({n_blocks} blocks of {table_numel} values and {observed_bytes} record bytes, "
            f"{n_decoder} decoder values, "
            f"{n_kf} keyframes)"
        )
    offset = header_bytes
    blocks = []
    for _ in range(n_blocks):
        block_id, cx, cy, cz = _BLOCK_HEAD.unpack_from(buf, offset)
        offset += _BLOCK_HEAD.size
        table = np.frombuffer(buf, "<f4", table_numel, offset)
        offset += 4 * table_numel
        observed = np.frombuffer(buf, np.uint8, observed_bytes, offset)
        offset += observed_bytes
        blocks.append(BlockState(block_id, np.array([cx, cy, cz], dtype=np.float32), table, observed))
    decoders = np.frombuffer(buf, "<f4", n_decoder, offset)
    offset += 4 * n_decoder
    stamps = np.frombuffer(buf, "<i8", n_kf, offset)
    offset += 8 * n_kf
    poses = np.frombuffer(buf, "<f8", 16 * n_kf, offset).reshape(n_kf, 4, 4)
    return MapUpdate(version, ack, blocks, decoders, stamps, poses, loop_stamp, epoch, durable)


def apply(update: MapUpdate, block_map: BlockMap) -> list[int]:
    """Write the update's blocks (creating new ones) and decoders into ``block_map``, and add the blocks'
    observed-space records to its own; returns the ids of the blocks it created. Keyframe poses are the
    caller's (they belong to its pose bookkeeping)."""
    n_decoder = sum(p.numel() for p in block_map.decoders.parameters())
    if update.decoders.size != n_decoder:
        raise MapUpdateError(
            f"map update has {update.decoders.size} decoder values, this map's decoders have "
            f"{n_decoder} (different decoder config?)"
        )
    created = []
    for state in sorted(update.blocks, key=lambda b: b.block_id):
        if state.block_id > len(block_map):
            raise MapUpdateError(
                f"map update has block {state.block_id}, but this map has only "
                f"{len(block_map)} blocks (an update was lost)"
            )
        if state.block_id == len(block_map):
            block_map.add_block(torch.from_numpy(state.centre_world.copy()))
            created.append(state.block_id)
        block = block_map.blocks[state.block_id]
        if not np.allclose(block.centre.detach().cpu().numpy(), state.centre_world, atol=1e-6):
            raise MapUpdateError(
                f"map update moves block {state.block_id} from {block.centre.tolist()} to "
                f"{state.centre_world.tolist()}: the maps diverged"
            )
        if state.table.size != block.grid.table.numel():
            raise MapUpdateError(
                f"map update block {state.block_id} has {state.table.size} table values, this "
                f"map's blocks have {block.grid.table.numel()} (different grid config?)"
            )
        with torch.no_grad():
            block.grid.table.copy_(torch.from_numpy(state.table.copy()).view_as(block.grid.table))
        if state.observed.size:
            n = block.observed.numel()
            if state.observed.size != (n + 7) // 8:
                raise MapUpdateError(
                    f"map update block {state.block_id} has a {state.observed.size}-byte observed-space "
                    f"record, this map's blocks have {n} voxels (different block.observed_voxel_m?)"
                )
            bits = np.unpackbits(state.observed, count=n, bitorder="little").astype(bool)
            # a union: a tracker records its newest keyframes itself before the mapper has them
            block.observed |= torch.from_numpy(bits).view_as(block.observed)
    with torch.no_grad():
        vec = torch.from_numpy(update.decoders.copy()).to(block_map.device)
        torch.nn.utils.vector_to_parameters(vec, block_map.decoders.parameters())
    return created
