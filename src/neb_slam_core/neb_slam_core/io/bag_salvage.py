"""Reading what a crash left of a ROS 2 bag: a storage file cut short, or no metadata.yaml.

A recorder that is killed (or loses power, or fills the disk) leaves its last storage file without its
end: an MCAP file without its summary and footer, an SQLite file shorter than its header says.
``rosbags`` refuses such files as a whole ("File end magic is invalid", "database disk image is
malformed"), and a directory whose recorder never wrote metadata.yaml is not a bag to it at all. Both
formats are written front to back, so everything before the damage is intact. :func:`salvage_bag`
reads it, the way ``ros2 bag reindex`` (metadata) and ``mcap recover`` (data) would recover a bag, and
returns a reader with the small part of ``rosbags.highlevel.AnyReader``'s interface that the bag
loader uses (``topics``, ``messages``, ``deserialize``, ``close``) plus a one-line account of the
damage, which the loader logs once.

- MCAP: records are read in order from the start: schemas, channels, messages, and chunks (whose
  records are read the same way). Reading stops at the first incomplete record. In an uncompressed
  chunk that the cut went through, the complete records before the cut are still read; a compressed
  chunk that the cut went through is lost as a whole (its compressed stream cannot be checked).
  The PyPI package ``mcap`` has a stream reader that reads records in order too, but it gives
  records, not where they lie in the file: the loader fetches single frames later by position, which
  it could then only do by decoding the stream from the start again. The records needed here are few
  and simple (an opcode, a length, fixed fields), and ``rosbags``, which the loader needs anyway,
  provides the chunk decompressors, so this module reads them itself and adds no dependency.
- SQLite: the file is opened read-only with ``PRAGMA writable_schema``, with which SQLite opens a file
  shorter than its header says instead of refusing it. Messages are read in row order until the first
  one SQLite cannot read; the rows before it are used.

Messages are decoded with the ROS 2 Jazzy message definitions (what the bag loader uses for every ROS 2
bag), not with the definitions stored in the bag.
"""

from __future__ import annotations

import contextlib
import os
import re
import sqlite3
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from ..errors import DatasetError

MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
STORAGE_SUFFIXES = (".mcap", ".db3")

# MCAP record opcodes (https://mcap.dev/spec)
_OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_DATA_END = 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # message start time, end time, uncompressed size, CRC


@dataclass(frozen=True)
class SalvagedConnection:
    """One topic of a salvaged bag (all its storage files together)."""

    id: int
    topic: str
    msgtype: str


@dataclass(frozen=True)
class SalvagedTopic:
    msgtype: str
    msgcount: int
    connections: list[SalvagedConnection]


@dataclass
class _Chunk:
    """A compressed MCAP chunk, decompressed when one of its messages is fetched."""

    file: int
    data_offset: int
    compressed_size: int
    uncompressed_size: int
    compression: str
    crc: int


@dataclass
class _Index:
    """Where every salvaged message lies, in storage order, as the scans find them."""

    conn: list[int] = field(default_factory=list)
    log_ns: list[int] = field(default_factory=list)
    file: list[int] = field(default_factory=list)
    chunk: list[int] = field(default_factory=list)  # -1: ``offset`` is in the file (or a row id)
    offset: list[int] = field(default_factory=list)
    length: list[int] = field(default_factory=list)

    def add(self, conn: int, log_ns: int, file: int, chunk: int, offset: int, length: int) -> None:
        for column, value in zip(
            (self.conn, self.log_ns, self.file, self.chunk, self.offset, self.length),
            (conn, log_ns, file, chunk, offset, length),
        ):
            column.append(value)


def storage_files(root: Path) -> list[Path]:
    """The storage files of a bag: ``root`` itself for a file; for a directory, the files metadata.yaml
    lists (those that exist), else its ``.mcap`` and ``.db3`` files in split order (``name_0``,
    ``name_1``, ..., by the number)."""
    if not root.is_dir():
        return [root]
    listed = [root / Path(p).name for p in _metadata(root).get("relative_file_paths") or []]
    if listed and all(p.is_file() for p in listed):
        return listed

    def split_number(p: Path) -> tuple[int, str]:
        m = re.search(r"_(\d+)$", p.stem)
        return (int(m.group(1)) if m else -1, p.name)

    return sorted((p for p in root.iterdir() if p.suffix in STORAGE_SUFFIXES and p.is_file()), key=split_number)


def _metadata(root: Path) -> dict:
    """metadata.yaml's ``rosbag2_bagfile_information``, or {} when it is missing or unreadable."""
    try:
        info = yaml.safe_load((root / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return {}
    return info if isinstance(info, dict) else {}


def find_damage(path: Path) -> str | None:
    """How the storage file ``path`` is cut short (one phrase), or None when its length is whole."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(100)
        if path.suffix == ".mcap":
            if not head.startswith(MCAP_MAGIC):
                return None  # not an MCAP file at all: not damage this module reads around
            if size < 2 * len(MCAP_MAGIC):
                return f"only {size} bytes"
            f.seek(size - len(MCAP_MAGIC))
            return None if f.read() == MCAP_MAGIC else "no end (summary and footer missing)"
    if not (head.startswith(SQLITE_MAGIC) or SQLITE_MAGIC.startswith(head)):
        return None  # not an SQLite file at all
    if len(head) < 100:
        return f"only {size} bytes, not even a whole SQLite header"
    page_size = int.from_bytes(head[16:18], "big")
    page_size = 65536 if page_size == 1 else page_size
    declared = page_size * int.from_bytes(head[28:32], "big")
    return f"{size} of the {declared} bytes its header declares" if size < declared else None


class SalvagedBag:
    """The readable messages of a damaged ROS 2 bag (module docstring), indexed once when built.

    Args:
        root: the bag directory or storage file.
        files: its storage files in order.

    Attributes:
        report: what was damaged and what was read, one line.
    """

    def __init__(self, root: Path, files: list[Path]):
        self.root = root
        self.files = list(files)
        self._typestore = None
        self._handles: dict[int, object] = {}
        self._handles_pid = os.getpid()
        self._chunks: list[_Chunk] = []
        self._chunk_cache: tuple[int, bytes] | None = None
        self._conn_ids: dict[tuple[str, str], int] = {}
        index = _Index()
        notes = []
        for k, path in enumerate(self.files):
            damage = find_damage(path)
            scan = self._scan_mcap if path.suffix == ".mcap" else self._scan_sqlite
            note = scan(k, path, index)
            if damage is not None or note is not None:
                notes.append(f"{path.name}: {damage or 'damaged'}" + (f", {note}" if note else ""))
        order = np.argsort(np.asarray(index.log_ns, dtype=np.int64), kind="stable")
        self._conn = np.asarray(index.conn, dtype=np.int64)[order]
        self._log_ns = np.asarray(index.log_ns, dtype=np.int64)[order]
        self._file = np.asarray(index.file, dtype=np.int64)[order]
        self._chunk = np.asarray(index.chunk, dtype=np.int64)[order]
        self._offset = np.asarray(index.offset, dtype=np.int64)[order]
        self._length = np.asarray(index.length, dtype=np.int64)[order]
        self.connections = [SalvagedConnection(i, t, m) for (t, m), i in self._conn_ids.items()]
        self.report = self._report(notes)

    def __len__(self) -> int:
        """How many messages were salvaged."""
        return len(self._conn)

    # ------------------------------------------------------------------------------------------
    # the reader interface

    @property
    def topics(self) -> dict[str, SalvagedTopic]:
        counts = np.bincount(self._conn, minlength=len(self.connections))
        return {
            c.topic: SalvagedTopic(c.msgtype, int(counts[c.id]), [c])
            for c in sorted(self.connections, key=lambda c: c.topic)
        }

    def messages(self, connections=(), start: int | None = None, stop: int | None = None):
        """``(connection, log time ns, raw CDR bytes)`` of the salvaged messages of ``connections`` (all
        when empty) with ``start <= log time < stop``, in log-time order (storage order on ties)."""
        # the index is sorted by log time: the window is a slice of it
        lo = 0 if start is None else int(np.searchsorted(self._log_ns, start, side="left"))
        hi = len(self._log_ns) if stop is None else int(np.searchsorted(self._log_ns, stop, side="left"))
        rows = np.arange(lo, max(lo, hi))
        if connections:
            rows = rows[np.isin(self._conn[rows], [c.id for c in connections])]
        for i in rows:
            yield self.connections[self._conn[i]], int(self._log_ns[i]), self._fetch(int(i))

    def deserialize(self, raw: bytes, msgtype: str):
        if self._typestore is None:
            from .bag import ros2_typestore

            self._typestore = ros2_typestore()
        return self._typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        """Close the storage files (a later read opens them again)."""
        if self._handles_pid == os.getpid():
            for handle in self._handles.values():
                with contextlib.suppress(Exception):  # closing is best effort
                    handle.close()
        self._handles = {}
        self._chunk_cache = None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_handles"], state["_chunk_cache"], state["_typestore"] = {}, None, None
        return state

    # ------------------------------------------------------------------------------------------
    # reading one message

    def _handle(self, k: int):
        if self._handles_pid != os.getpid():  # a forked process opens its own
            self._handles, self._handles_pid = {}, os.getpid()
        if k not in self._handles:
            path = self.files[k]
            self._handles[k] = path.open("rb") if path.suffix == ".mcap" else _open_sqlite(path)
        return self._handles[k]

    def _fetch(self, i: int) -> bytes:
        k, chunk, offset, length = int(self._file[i]), int(self._chunk[i]), int(self._offset[i]), int(self._length[i])
        handle = self._handle(k)
        if self.files[k].suffix == ".db3":
            row = handle.execute("SELECT data FROM messages WHERE id = ?", (offset,)).fetchone()
            return bytes(row[0])
        if chunk < 0:
            handle.seek(offset)
            return handle.read(length)
        return self._chunk_data(chunk)[offset : offset + length]

    def _chunk_data(self, c: int) -> bytes:
        if self._chunk_cache is None or self._chunk_cache[0] != c:
            self._chunk_cache = (c, self._decompress(self._chunks[c]))
        return self._chunk_cache[1]

    def _decompress(self, chunk: _Chunk) -> bytes:
        from rosbags.rosbag2.storage_mcap import decompress

        handle = self._handle(chunk.file)
        handle.seek(chunk.data_offset)
        return decompress(handle.read(chunk.compressed_size), chunk.compression, chunk.uncompressed_size, chunk.crc)

    # ------------------------------------------------------------------------------------------
    # scans

    def _connection(self, topic: str, msgtype: str) -> int:
        return self._conn_ids.setdefault((topic, msgtype), len(self._conn_ids))

    def _scan_mcap(self, k: int, path: Path, index: _Index) -> str | None:
        """Index the complete records of MCAP file ``path`` in order; returns where reading stopped
        and why, or None when it reached the end of the data section."""
        size = path.stat().st_size
        schemas: dict[int, str] = {}
        channels: dict[int, int] = {}  # channel id -> connection id

        def take(op: int, raw: bytes, chunk: int, data_at: int, length: int) -> None:
            """Index a schema, channel or message record from its body ``raw`` (for a message, its
            head is enough: its data lies at ``data_at`` in the file, or in compressed chunk ``chunk``)."""
            if op == _OP_SCHEMA:
                (schema_id,) = struct.unpack_from("<H", raw)
                schemas[schema_id] = _mcap_string(raw, 2)
            elif op == _OP_CHANNEL:
                channel_id, schema_id = struct.unpack_from("<HH", raw)
                if schema_id in schemas:  # schemaless channels carry nothing the loader decodes
                    channels[channel_id] = self._connection(_mcap_string(raw, 4), schemas[schema_id])
            elif op == _OP_MESSAGE and length >= _MESSAGE_HEAD.size:
                channel_id, _, log_ns, _ = _MESSAGE_HEAD.unpack_from(raw)
                if channel_id in channels:
                    index.add(channels[channel_id], log_ns, k, chunk, data_at, length - _MESSAGE_HEAD.size)

        with path.open("rb") as f:

            def read_at(pos: int, n: int) -> bytes:
                f.seek(pos)
                return f.read(n)

            def scan(start: int, end: int, chunk_at: int | None) -> str | None:
                """Index the records in the file's bytes [start, end) (a chunk's records when
                ``chunk_at`` is the chunk's offset); returns why it stopped early, or None."""
                pos = start
                while pos < end:
                    head = read_at(pos, _RECORD_HEAD.size) if pos + _RECORD_HEAD.size <= end else b""
                    if not head:
                        return f"read up to byte {pos}, where a record is cut short"
                    op, length = _RECORD_HEAD.unpack(head)
                    body = pos + _RECORD_HEAD.size
                    if chunk_at is None and op in (_OP_DATA_END, _OP_FOOTER):
                        return None
                    if op == _OP_CHUNK and chunk_at is None:
                        note = scan_chunk(pos, body, min(body + length, size))
                        if note is not None:
                            return note
                    elif body + length > end:
                        where = "" if chunk_at is None else f" in the chunk at byte {chunk_at}"
                        return f"read up to byte {pos}, where {_mcap_kind(op)}{where} is cut short"
                    elif op in (_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE):
                        n = min(length, _MESSAGE_HEAD.size) if op == _OP_MESSAGE else length
                        take(op, read_at(body, n), -1, body + _MESSAGE_HEAD.size, length)
                    pos = body + length
                return None if chunk_at is not None else f"ends at byte {pos} without the end of its data"

            def scan_chunk(pos: int, body: int, end: int) -> str | None:
                head = read_at(body, _CHUNK_HEAD.size + 4)
                whole_head = len(head) == _CHUNK_HEAD.size + 4
                name_len = struct.unpack_from("<I", head, _CHUNK_HEAD.size)[0] if whole_head else 0
                data_at = body + len(head) + name_len + 8
                if not whole_head or data_at > end:
                    return f"read up to byte {pos}, where a chunk record is cut short"
                _, _, uncompressed_size, crc = _CHUNK_HEAD.unpack_from(head)
                compression = read_at(body + len(head), name_len).decode()
                (compressed_size,) = struct.unpack("<Q", read_at(data_at - 8, 8))
                if not compression:  # the records lie in the file as they are
                    note = scan(data_at, min(data_at + compressed_size, end), pos)
                    if note is None and data_at + compressed_size > end:
                        note = f"read up to byte {end}, where the chunk at byte {pos} is cut short"
                    return note
                if data_at + compressed_size > end:
                    return f"read up to byte {pos}, where a compressed chunk is cut short (lost whole)"
                self._chunks.append(_Chunk(k, data_at, compressed_size, uncompressed_size, compression, crc))
                data = self._decompress(self._chunks[-1])
                inner = 0
                while inner + _RECORD_HEAD.size <= len(data):
                    op, length = _RECORD_HEAD.unpack_from(data, inner)
                    at = inner + _RECORD_HEAD.size
                    take(op, data[at : at + length], len(self._chunks) - 1, at + _MESSAGE_HEAD.size, length)
                    inner = at + length
                return None

            if read_at(0, len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise DatasetError(path, "not an MCAP file (it does not start with the MCAP magic)")
            return scan(len(MCAP_MAGIC), size, None)

    def _scan_sqlite(self, k: int, path: Path, index: _Index) -> str | None:
        """Index the readable rows of the rosbag2 SQLite file ``path`` in row order; returns where
        reading stopped, or None when every row was read."""
        try:
            con = _open_sqlite(path)
            topics = con.execute("SELECT id, name, type FROM topics").fetchall()
        except sqlite3.DatabaseError as exc:
            raise DatasetError(path, f"cannot read the bag's topics table: {exc}") from None
        conn_of = {tid: self._connection(name, msgtype) for tid, name, msgtype in topics}
        last_id = 0
        try:
            # the data is read here too: a row is indexed only if all of it can be read
            rows = con.execute("SELECT id, topic_id, timestamp, data FROM messages ORDER BY id")
            for row_id, topic_id, log_ns, data in rows:
                if topic_id in conn_of:
                    index.add(conn_of[topic_id], log_ns, k, -1, row_id, len(data))
                last_id = row_id
        except sqlite3.DatabaseError as exc:
            return f"rows after id {last_id} unreadable ({exc})"
        finally:
            con.close()
        return None

    # ------------------------------------------------------------------------------------------

    def _report(self, notes: list[str]) -> str:
        counts = np.bincount(self._conn, minlength=len(self.connections))
        got = {c.topic: int(counts[c.id]) for c in self.connections}
        read = f"{len(self._conn)} messages read"
        if len(self._log_ns):
            read += f" (log time {self._log_ns.min() * 1e-9:.3f} to {self._log_ns.max() * 1e-9:.3f} s)"
        listed = {}
        if self.root.is_dir():
            for entry in _metadata(self.root).get("topics_with_message_count") or []:
                with contextlib.suppress(KeyError, TypeError):
                    listed[entry["topic_metadata"]["name"]] = int(entry["message_count"])
        if listed:
            lost = [f"{t} {n - got.get(t, 0)} of {n}" for t, n in sorted(listed.items()) if got.get(t, 0) < n]
            lost_text = "lost per metadata.yaml: " + (", ".join(lost) if lost else "nothing")
        else:
            lost_text = "how many were lost is unknown without metadata.yaml's counts"
        if self.root.is_dir() and not (self.root / "metadata.yaml").is_file():
            notes = ["metadata.yaml missing", *notes]
        return f"{'; '.join(notes)}; {read}; {lost_text}"


def salvage_bag(root: Path) -> SalvagedBag | None:
    """A reader of the readable part of the ROS 2 bag ``root`` when it is damaged as the module
    docstring says; None when it shows no such damage (then whatever else ``rosbags`` refused it for
    stands). Raises :class:`DatasetError` naming the file when nothing can be read."""
    files = storage_files(root)
    if not files:
        return None
    no_metadata = root.is_dir() and not (root / "metadata.yaml").is_file()
    if not no_metadata and all(find_damage(f) is None for f in files):
        return None
    bag = SalvagedBag(root, files)
    if len(bag) == 0:
        raise DatasetError(root, f"damaged bag with no readable message ({bag.report})")
    return bag


def _open_sqlite(path: Path) -> sqlite3.Connection:
    """``path`` read-only; ``writable_schema`` makes SQLite open a file shorter than its header says
    (it then reads the pages that are there) instead of calling the whole file malformed."""
    con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, check_same_thread=False)
    con.execute("PRAGMA writable_schema=ON")
    return con


def _mcap_string(raw: bytes, at: int) -> str:
    """The MCAP string (uint32 length, UTF-8) at byte ``at`` of ``raw``."""
    (n,) = struct.unpack_from("<I", raw, at)
    return raw[at + 4 : at + 4 + n].decode()


def _mcap_kind(op: int) -> str:
    names = {_OP_SCHEMA: "schema", _OP_CHANNEL: "channel", _OP_MESSAGE: "message", _OP_CHUNK: "chunk"}
    return f"a {names[op]} record" if op in names else f"a record (opcode {op:#04x})"
