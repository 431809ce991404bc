"""The map update: the part of a block map that a mapping step changed, as one versioned byte string.

The mapper sends it (ROS topic ``map_update``, std_msgs/UInt8MultiArray) to trackers that hold a copy of
the map: the hash tables and observed-space records of the blocks it changed, all decoder parameters,
and the current poses of all keyframes (mapping refines them). A receiver's observed-space record
becomes the union of its own and the mapper's.

A block goes whole (its first time, or when most of it changed) or as what changed since the receivers
last got it: the sender keeps what the receivers hold (:class:`ReceiverMirror`), and sends either the
table rows with a value more than ``tolerance`` off it, or, with a ``delta_step``, every value's change
as a whole number of steps, in one byte a value (two where a change in the block needs more than
-127..127; a change beyond -32767..32767 goes on in the next updates), deflate-compressed. Table values
of whole blocks and rows go as float32, or as float16 when the sender asks for it (decoders and poses
always at full precision). Applying every update in order gives each receiver the mirror's tables
exactly: with tolerance 0, no step and float32 the mapper's map itself; otherwise every table value
within ``tolerance`` (rows) or half a step (changes in steps) of the mapper's, plus float16's rounding
where a block last went whole.

The step is a power of two, so that a change times the step is exact in float32 and the receiver's sum
(one float32 addition per value) is the mirror's, bit for bit.

A mapper that checkpoints says which of its keyframes a restart would keep (``durable_keyframes``), and
every start of a mapper has its own ``epoch``: a receiver that sees a new epoch knows the sender restarted
(from a checkpoint, with the keyframes the update's poses list), starts counting versions anew and hands it
the keyframes it lacks.

Binary layout, version 5, little-endian, no padding::

    header (84 bytes)
      char[4]  magic            b"NEBU"
      uint16   format           5 (1: without observed_bytes, 2: without epoch and durable_keyframes,
                                3: without the row fields, float32 tables only, 4: without the delta
                                fields; all still read)
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
      uint32   n_partial        P, blocks sent as changed rows; format 4
      uint16   row_width        F, table values per row (the features of one entry); format 4
      uint16   value_bytes      4: table values are float32, 2: float16; format 4
      uint32   n_delta          D, blocks sent as changes in steps; format 5
      float32  delta_step       the step of those changes (a power of two; 0 when D is 0); format 5
    B times (whole blocks)
      uint32   block_id
      float32  centre_world[3]  metres
      value    table[table_numel]   the block's hash table, row-major (entries, features)
      uint8    observed[observed_bytes]  the block's (V, V, V) record of observed voxels
                                (:class:`~.block.NeuralBlock`), flattened row-major, 8 voxels a byte,
                                least significant bit first
    P times (blocks sent as changed rows; format 4)
      uint32   block_id
      float32  centre_world[3]
      uint32   n_rows           R
      uint32   rows[R]          row indices, increasing
      value    values[R][F]     those rows of the table
      uint8    observed[observed_bytes]
    D times (blocks sent as changes in steps; format 5)
      uint32   block_id
      float32  centre_world[3]
      uint8    step_bytes       1: the changes are int8, 2: int16
      uint32   packed_bytes     N
      uint8    packed[N]        zlib stream of the changes, one per table value: its change in steps,
                                which the receiver adds (times ``delta_step``) to the value it holds;
                                with 2 step_bytes, the low bytes of all values, then their high bytes
      uint8    observed[observed_bytes]
    float32  decoders[n_decoder]    parameters in ``Decoders.parameters()`` order, each row-major
    int64    keyframe_stamps_ns[K]
    float64  keyframe_poses[K][4][4]   T_world_cam of keyframes 0..K-1, row-major

Block ids are dense (0, 1, 2, ...): a receiver that does not have block ``id`` yet creates it, and it
must then have every lower id already; a block's first update is whole.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

import numpy as np
import torch

from ..config import is_delta_step
from ..errors import NebSlamError
from .block_map import BlockMap

MAGIC = b"NEBU"
FORMAT_VERSION = 5
READABLE_FORMATS = (1, 2, 3, 4, 5)
_HEADER = struct.Struct("<4sHHQqIIIII")  # the first 44 bytes; header_bytes says where the blocks start
_HEADER_EXTRA = struct.Struct("<qI")  # fields appended since: loop_stamp_ns, observed_bytes (format 2)
_HEADER_RESTART = struct.Struct("<Qi")  # epoch, durable_keyframes (format 3)
_HEADER_ROWS = struct.Struct("<IHH")  # n_partial, row_width, value_bytes (format 4)
_HEADER_DELTA = struct.Struct("<If")  # n_delta, delta_step (format 5)
_HEADER_SIZE = _HEADER.size + _HEADER_EXTRA.size + _HEADER_RESTART.size + _HEADER_ROWS.size + _HEADER_DELTA.size
_LOOP_STAMP = struct.Struct("<q")
_BLOCK_HEAD = struct.Struct("<I3f")
_N_ROWS = struct.Struct("<I")
_VALUE_TYPES = {4: "<f4", 2: "<f2"}
FLOAT16_MAX = float(np.finfo(np.float16).max)
#: the types of changes in steps by their size, and the largest change each carries (symmetric)
_STEP_TYPES = {1: ("<i1", 127), 2: ("<i2", 32767)}
_STEP_HEAD = struct.Struct("<BI")  # step_bytes, packed_bytes
#: zlib's level for the changes in steps: its fastest (the higher levels shrink them by a few per cent)
DEFLATE_LEVEL = 1


class MapUpdateError(NebSlamError):
    """A map update is malformed or does not fit the receiving map."""


@dataclass
class BlockState:
    """One block's identity and parameters: ``table`` is the float32 table ``(table_numel,)``, or with
    ``rows`` (increasing row indices) those rows only, ``(len(rows) * row_width,)``; with ``steps``
    (int8 or int16, ``(table_numel,)``) the table's change in the update's ``delta_step`` instead, and
    ``table`` empty; ``observed`` its observed-space record packed 8 voxels a byte
    (:func:`pack_observed`), empty without one."""

    block_id: int
    centre_world: np.ndarray
    table: np.ndarray
    observed: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    rows: np.ndarray | None = None
    steps: np.ndarray | None = None

    @property
    def whole(self) -> bool:
        return self.rows is None and self.steps is None


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
    row_width: int = 1
    value_bytes: int = 4
    delta_step: float = 0.0

    @property
    def block_ids(self) -> list[int]:
        return [b.block_id for b in self.blocks]


class ReceiverMirror:
    """The sender's copy of the tables its receivers hold, as its updates left them: what decides which
    rows an update carries (module docstring). ``tolerance``: a row goes once one of its values is more
    than this off the receivers' copy (0: every change); ``float16``: table values go as float16 (an
    update whose tables hold a value beyond float16's range goes as float32). A row's change is that of
    the values it would be sent as, so with float16 a change within the rounding sends nothing.
    ``delta_step`` (0, or a power of two): a block the receivers have goes as its values' changes in
    whole steps instead of rows (``tolerance`` then plays no part), whole blocks as above."""

    def __init__(self, tolerance: float = 0.0, float16: bool = False, delta_step: float = 0.0):
        if tolerance < 0:
            raise ValueError(f"tolerance must be >= 0, got {tolerance}")
        if not is_delta_step(delta_step):
            raise ValueError(f"delta_step must be 0 or a power of two at most 1, got {delta_step}")
        self.tolerance = tolerance
        self.float16 = float16
        self.delta_step = float(delta_step)
        self._tables: dict[int, np.ndarray] = {}  # block id -> (rows, F), as the receivers have it

    def blocks(self, block_map: BlockMap, block_ids, whole: bool = False) -> tuple[list[BlockState], int]:
        """The states of blocks ``block_ids`` for the next update, and its value bytes (4 or 2); the
        mirror then holds what the receivers will have. ``whole``: every block whole (a receiver that
        starts over)."""
        ids = sorted(int(b) for b in block_ids)
        # views of the tables (the caller holds the map still while it captures): read for the changes
        # in steps, copied for values
        tables = {i: _table_rows(block_map.blocks[i]) for i in ids}
        stepped = {i for i in ids if self._goes_in_steps(i, tables[i].shape, whole)}
        valued = [tables[i] for i in ids if i not in stepped]
        fits = self.float16 and all(float(np.abs(t).max(initial=0.0)) <= FLOAT16_MAX for t in valued)
        value_bytes = 2 if fits else 4
        states = []
        for i in ids:
            block, table = block_map.blocks[i], tables[i]
            centre = block.centre.detach().cpu().numpy().astype(np.float32)
            observed = pack_observed(block.observed)
            if i in stepped:
                steps = self._steps(self._tables[i], table)
                states.append(BlockState(i, centre, np.zeros(0, np.float32), observed, steps=steps))
                continue
            held = self._tables.get(i)
            wire = table.astype(_VALUE_TYPES[value_bytes], copy=True)  # what the receivers get
            rows = None
            if held is not None and not whole and held.shape == wire.shape and held.dtype == wire.dtype:
                # what would go against what is there: a value float16 rounds to the held one has not moved
                moved = np.abs(wire.astype(np.float32, copy=False) - held.astype(np.float32, copy=False)).max(axis=1)
                changed = np.flatnonzero(moved > self.tolerance).astype(np.uint32)
                # an index costs 4 bytes: past about half the rows the whole table is smaller
                if changed.size * (4 + table.shape[1] * value_bytes) < table.size * value_bytes:
                    rows = changed
            if rows is None:
                # kept as sent: float16 halves the mirror too, unless changes in steps go onto it
                self._tables[i] = wire.astype(np.float32) if self.delta_step else wire
                values = wire.reshape(-1).astype(np.float32)  # a copy: the mirror's rows change in place
            else:
                held[rows] = wire[rows]
                values = wire[rows].reshape(-1).astype(np.float32, copy=False)  # indexing copied
            states.append(BlockState(i, centre, values, observed, rows))
        return states, value_bytes

    def _goes_in_steps(self, block_id: int, shape: tuple[int, ...], whole: bool) -> bool:
        """Whether block ``block_id`` (a table of ``shape``) goes as changes in steps: with a step, to
        receivers that hold it (and are not starting over)."""
        held = self._tables.get(block_id)
        return bool(self.delta_step) and not whole and held is not None and held.shape == shape

    def _steps(self, held: np.ndarray, table: np.ndarray) -> np.ndarray:
        """The change from ``held`` (float32, updated in place as the receivers will have it) towards
        ``table`` in whole steps ``(table.size,)``: int8 where every change fits, int16 otherwise."""
        step = np.float32(self.delta_step)
        steps = np.rint((table - held) / step).reshape(-1)
        largest = float(np.abs(steps).max(initial=0.0))
        dtype, limit = _STEP_TYPES[1 if largest <= _STEP_TYPES[1][1] else 2]
        steps = np.clip(steps, -limit, limit).astype(dtype)
        held += step_values(steps, self.delta_step).reshape(held.shape)
        return steps


def step_values(steps: np.ndarray, delta_step: float) -> np.ndarray:
    """Changes in steps as float32 values: exact, the step being a power of two. Sender and receivers
    add exactly these, so that they hold the same values."""
    return steps.astype(np.float32) * np.float32(delta_step)


def _table_rows(block) -> np.ndarray:
    """A block's table as float32 ``(rows, row_width)``: a view of a float32 CPU table (it changes with
    the map), else a copy."""
    table = block.grid.table.detach().cpu()
    return table.reshape(-1, table.shape[-1]).numpy().astype(np.float32, copy=False)


def capture(
    block_map: BlockMap,
    block_ids,
    version: int,
    ack_stamp_ns: int,
    keyframe_stamps_ns,
    keyframe_poses,
    loop_stamp_ns: int = -1,
    mirror: ReceiverMirror | None = None,
    whole: bool = False,
) -> MapUpdate:
    """The update carrying blocks ``block_ids`` of ``block_map``, its decoders and the keyframe poses
    ``(K, 4, 4)`` with their stamps ``(K,)``, as copies (another thread or process may apply or encode it
    while the map moves on); ``loop_stamp_ns`` names the newest loop correction in it. With ``mirror``
    the blocks go as it decides (changed rows or changes in steps, float16), ``whole`` all of them whole;
    without it whole and exact. The map must hold still while this runs (the mapper holds its lock)."""
    stamps = np.array(keyframe_stamps_ns, dtype=np.int64).reshape(-1)
    poses = np.array(keyframe_poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(stamps) != len(poses):
        raise ValueError(f"{len(stamps)} keyframe stamps for {len(poses)} poses")
    mirror = mirror or ReceiverMirror()
    blocks, value_bytes = mirror.blocks(block_map, block_ids, whole=whole)
    row_width = int(block_map.blocks[0].grid.table.shape[-1]) if len(block_map) else 1
    decoders = torch.nn.utils.parameters_to_vector(block_map.decoders.parameters()).detach().cpu().numpy().copy()
    update = MapUpdate(version, ack_stamp_ns, blocks, decoders, stamps, poses, loop_stamp_ns)
    update.row_width, update.value_bytes = row_width, value_bytes
    if any(b.steps is not None for b in blocks):
        update.delta_step = mirror.delta_step
    return update


def encode(update: MapUpdate) -> bytes:
    """``update`` in the binary layout of the module docstring."""

    def kind(test):
        return sorted((b for b in update.blocks if test(b)), key=lambda b: b.block_id)

    whole = kind(lambda b: b.whole)
    partial = kind(lambda b: b.rows is not None)
    delta = kind(lambda b: b.steps is not None)
    table_numel = whole[0].table.size if whole else delta[0].steps.size if delta else 0
    observed_bytes = update.blocks[0].observed.size if update.blocks else 0
    if delta and not (update.delta_step > 0 and is_delta_step(update.delta_step)):
        raise ValueError(f"blocks in steps need a delta_step that is a power of two, got {update.delta_step}")
    for b in update.blocks:
        size = b.table.size if b.steps is None else b.steps.size
        if (b.rows is None and size != table_numel) or b.observed.size != observed_bytes:
            raise ValueError(f"block {b.block_id}'s table or record differs in size from the update's first block")
        if b.rows is not None and b.table.size != len(b.rows) * update.row_width:
            raise ValueError(f"block {b.block_id} has {b.table.size} values for {len(b.rows)} rows")
    value = _VALUE_TYPES[update.value_bytes]
    stamps = np.ascontiguousarray(update.keyframe_stamps_ns, dtype="<i8").reshape(-1)
    poses = np.ascontiguousarray(update.keyframe_poses, dtype="<f8").reshape(-1, 4, 4)
    parts = [
        _HEADER.pack(
            MAGIC,
            FORMAT_VERSION,
            0,
            update.version,
            update.ack_stamp_ns,
            len(whole),
            table_numel,
            update.decoders.size,
            len(stamps),
            _HEADER_SIZE,
        ),
        _HEADER_EXTRA.pack(update.loop_stamp_ns, observed_bytes),
        _HEADER_RESTART.pack(update.epoch, update.durable_keyframes),
        _HEADER_ROWS.pack(len(partial), update.row_width, update.value_bytes),
        _HEADER_DELTA.pack(len(delta), update.delta_step if delta else 0.0),
    ]
    for b in whole + partial + delta:
        parts.append(_BLOCK_HEAD.pack(b.block_id, *map(float, b.centre_world)))
        if b.rows is not None:
            parts.append(_N_ROWS.pack(len(b.rows)))
            parts.append(np.asarray(b.rows).astype("<u4", copy=False).tobytes())
        if b.steps is not None:
            steps = np.asarray(b.steps)
            if steps.dtype.itemsize not in _STEP_TYPES or steps.dtype.kind != "i":
                raise ValueError(f"block {b.block_id}'s changes are {steps.dtype}, expected int8 or int16")
            width = steps.dtype.itemsize
            # byte planes: the high bytes of small changes are nearly all 0 or 255, which zlib packs well
            planes = steps.astype(_STEP_TYPES[width][0], copy=False).view(np.uint8).reshape(-1, width).T
            packed = zlib.compress(np.ascontiguousarray(planes).tobytes(), DEFLATE_LEVEL)
            parts += [_STEP_HEAD.pack(width, len(packed)), packed]
        else:
            parts.append(np.asarray(b.table).astype(value, copy=False).tobytes())
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
    n_partial, row_width, value_bytes = 0, 1, 4
    n_delta, delta_step = 0, 0.0
    if fmt >= 2 and header_bytes >= _HEADER.size + _HEADER_EXTRA.size:
        loop_stamp, observed_bytes = _HEADER_EXTRA.unpack_from(buf, _HEADER.size)
        if fmt >= 3 and header_bytes >= _HEADER.size + _HEADER_EXTRA.size + _HEADER_RESTART.size:
            epoch, durable = _HEADER_RESTART.unpack_from(buf, _HEADER.size + _HEADER_EXTRA.size)
        rows_at = _HEADER.size + _HEADER_EXTRA.size + _HEADER_RESTART.size
        if fmt >= 4 and header_bytes >= rows_at + _HEADER_ROWS.size:
            n_partial, row_width, value_bytes = _HEADER_ROWS.unpack_from(buf, rows_at)
        if fmt >= 5 and header_bytes >= _HEADER_SIZE:
            n_delta, delta_step = _HEADER_DELTA.unpack_from(buf, rows_at + _HEADER_ROWS.size)
    elif header_bytes >= _HEADER.size + _LOOP_STAMP.size:
        (loop_stamp,) = _LOOP_STAMP.unpack_from(buf, _HEADER.size)
    if value_bytes not in _VALUE_TYPES or row_width == 0:
        raise MapUpdateError(f"map update value_bytes {value_bytes} / row_width {row_width}: expected 4 or 2 / > 0")
    if n_delta and not (delta_step > 0 and is_delta_step(delta_step)):
        raise MapUpdateError(f"map update delta_step {delta_step}: expected a power of two at most 1")
    value = _VALUE_TYPES[value_bytes]

    def short(what: str, need: int, at: int) -> MapUpdateError:
        return MapUpdateError(
            f"map update of {len(buf)} bytes ends inside {what} (needs {need} bytes at {at}; header: "
            f"{n_blocks} whole, {n_partial} partial and {n_delta} delta blocks of {table_numel} values and "
            f"{observed_bytes} record bytes, {n_decoder} decoder values, {n_kf} keyframes)"
        )

    offset = header_bytes
    blocks = []
    for k in range(n_blocks + n_partial + n_delta):
        if offset + _BLOCK_HEAD.size > len(buf):
            raise short(f"block {k}'s head", _BLOCK_HEAD.size, offset)
        block_id, cx, cy, cz = _BLOCK_HEAD.unpack_from(buf, offset)
        centre = np.array([cx, cy, cz], dtype=np.float32)
        offset += _BLOCK_HEAD.size
        if k >= n_blocks + n_partial:  # sent as changes in steps
            if offset + _STEP_HEAD.size > len(buf):
                raise short(f"block {block_id}'s step size", _STEP_HEAD.size, offset)
            width, n_packed = _STEP_HEAD.unpack_from(buf, offset)
            offset += _STEP_HEAD.size
            if width not in _STEP_TYPES:
                raise MapUpdateError(f"map update block {block_id}: step_bytes {width}, expected 1 or 2")
            if offset + n_packed + observed_bytes > len(buf):
                raise short(f"block {block_id}'s changes", n_packed + observed_bytes, offset)
            steps = _inflate(buf[offset : offset + n_packed], table_numel, width, block_id)
            offset += n_packed
            observed = np.frombuffer(buf, np.uint8, observed_bytes, offset)
            offset += observed_bytes
            blocks.append(BlockState(block_id, centre, np.zeros(0, np.float32), observed, steps=steps))
            continue
        rows = None
        n_values = table_numel
        if k >= n_blocks:  # sent as changed rows
            if offset + _N_ROWS.size > len(buf):
                raise short(f"block {block_id}'s row count", _N_ROWS.size, offset)
            (n_rows,) = _N_ROWS.unpack_from(buf, offset)
            offset += _N_ROWS.size
            if offset + 4 * n_rows > len(buf):
                raise short(f"block {block_id}'s rows", 4 * n_rows, offset)
            rows = np.frombuffer(buf, "<u4", n_rows, offset)
            offset += 4 * n_rows
            n_values = n_rows * row_width
        need = value_bytes * n_values + observed_bytes
        if offset + need > len(buf):
            raise short(f"block {block_id}'s table", need, offset)
        table = np.frombuffer(buf, value, n_values, offset)
        table = table if value_bytes == 4 else table.astype(np.float32)
        offset += value_bytes * n_values
        observed = np.frombuffer(buf, np.uint8, observed_bytes, offset)
        offset += observed_bytes
        blocks.append(BlockState(block_id, centre, table, observed, rows))
    if len(buf) != offset + 4 * n_decoder + 136 * n_kf:
        raise MapUpdateError(
            f"map update of {len(buf)} bytes, its header announces {offset + 4 * n_decoder + 136 * n_kf} "
            f"({n_blocks} whole, {n_partial} partial and {n_delta} delta blocks of {table_numel} values and "
            f"{observed_bytes} record bytes, {n_decoder} decoder values, {n_kf} keyframes)"
        )
    decoders = np.frombuffer(buf, "<f4", n_decoder, offset)
    offset += 4 * n_decoder
    stamps = np.frombuffer(buf, "<i8", n_kf, offset)
    offset += 8 * n_kf
    poses = np.frombuffer(buf, "<f8", 16 * n_kf, offset).reshape(n_kf, 4, 4)
    return MapUpdate(
        version, ack, blocks, decoders, stamps, poses, loop_stamp, epoch, durable, row_width, value_bytes, delta_step
    )


def _inflate(packed, n: int, width: int, block_id: int) -> np.ndarray:
    """Block ``block_id``'s ``n`` changes in steps, ``width`` bytes each, from their zlib stream."""
    inflater = zlib.decompressobj()
    size = n * width
    try:
        raw = inflater.decompress(packed, size)
    except zlib.error as exc:
        raise MapUpdateError(f"map update block {block_id}: its changes do not inflate ({exc})") from exc
    if len(raw) != size or not inflater.eof or inflater.unconsumed_tail or inflater.unused_data:
        raise MapUpdateError(
            f"map update block {block_id}: its changes inflate to {len(raw)}{'+' if not inflater.eof else ''} "
            f"bytes in a stream of {len(packed)}, expected exactly {size}"
        )
    planes = np.frombuffer(raw, np.uint8).reshape(width, n)
    return np.ascontiguousarray(planes.T).view(_STEP_TYPES[width][0]).reshape(n)


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
        table = block.grid.table
        if state.steps is not None:
            if state.block_id in created:
                raise MapUpdateError(f"map update sends new block {state.block_id} as changes (an update was lost)")
            if state.steps.size != table.numel():
                raise MapUpdateError(
                    f"map update block {state.block_id} has {state.steps.size} changes, this map's blocks "
                    f"have {table.numel()} table values (different grid config?)"
                )
            with torch.no_grad():
                table.view(-1).add_(torch.from_numpy(step_values(state.steps, update.delta_step)).to(table.device))
        elif state.rows is None:
            if state.table.size != table.numel():
                raise MapUpdateError(
                    f"map update block {state.block_id} has {state.table.size} table values, this "
                    f"map's blocks have {table.numel()} (different grid config?)"
                )
            with torch.no_grad():
                table.copy_(torch.from_numpy(state.table.copy()).view_as(table))
        else:
            width = table.shape[-1]
            n_rows = table.numel() // width
            if state.rows.size and (update.row_width != width or int(state.rows.max()) >= n_rows):
                raise MapUpdateError(
                    f"map update block {state.block_id} has rows of {update.row_width} values up to row "
                    f"{int(state.rows.max())}, this map's tables have {n_rows} rows of {width} (different "
                    "grid config?)"
                )
            if state.block_id in created:
                raise MapUpdateError(f"map update sends new block {state.block_id} in part (an update was lost)")
            rows = torch.from_numpy(state.rows.astype(np.int64))
            values = torch.from_numpy(state.table.reshape(-1, width).copy())
            with torch.no_grad():
                table.view(-1, width)[rows] = values
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
