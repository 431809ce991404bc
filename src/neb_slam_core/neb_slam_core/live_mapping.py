"""The mapping side of the live engine (:class:`~neb_slam_core.live.LiveSlam`): mapping and loop closure,
in threads of the tracker's process or in a process of their own.

:class:`MappingSide` holds the mapper (:class:`~neb_slam_core.slam.Backend`, over its own copy of the map)
and the loop closer, each in a thread. Keyframes come in with :meth:`MappingSide.submit`; what goes back
to the tracker leaves through one callback, as ``(kind, payload)`` messages:

- ``"update"``: a :class:`~neb_slam_core.scene.map_update.MapUpdate` (the blocks a step changed, the
  decoders, the keyframe poses), after every mapping step and every chunk of background work;
- ``"loop"``: a :class:`~neb_slam_core.types.LoopEvent`, applied or not;
- ``"progress"``: :class:`Progress`, after every update and every keyframe the loop closer checked;
- ``"error"``: a thread failed (its name, the exception).

It runs in one of two places, with the same messages:

- in the tracker's process: the tracker makes a :class:`MappingSide` and gives it its own callback;
- in a child process (``live.mapping_process``): :class:`ProcessMapping`, the messages over a pipe.
  Python runs one thread of a process at a time (the GIL); the engine's threads run many short torch
  operations each, so in one process they take turns on the interpreter and two cores stay partly idle.
  A child process has an interpreter of its own: the tracker keeps one core, mapping and loop closure
  the other. The child is started with ``spawn`` (a forked copy of a process that runs torch's thread
  pools, or ROS's, is not safe) and imports the engine once, before the first frame.

Three rules keep the camera from waiting (the tracker's side is in :mod:`neb_slam_core.live`):

- the first frame's map is fitted with ``live.first_iterations`` map-only steps on every core the
  process may use; the rest of ``mapping.first_iterations`` runs in the background, one chunk of
  ``live.chunk_iterations`` after each mapping step (and while no keyframe waits);
- keyframes that queued up while the mapper was busy are integrated together, with one mapping step for
  all of them, so the mapping lag stays bounded by one step's worth of keyframes;
- a loop correction moves the keyframe poses at once; its two-stage re-optimisation runs in chunks in the
  same way, and a correction that arrives while one is being worked off replaces what is left of it.

The loop closer checks the newest keyframe when it is free: keyframes that queued up meanwhile are added
to its database unchecked, so its queue stays bounded too.
"""

from __future__ import annotations

import io
import logging
import multiprocessing
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from .config import SlamConfig
from .engine_process import lower_thread_priority, prepare_engine_process, usable_cores
from .loop.closer import LoopCloser
from .loop.correction import merge_correction
from .mapping.keyframes import KeyframeStore
from .scene import _ext, map_update
from .scene.block_map import BlockMap
from .slam import Backend
from .types import RgbdFrame

Emit = Callable[[str, object], None]

log = logging.getLogger(__name__)


@dataclass
class Handoff:
    """A keyframe on its way from the tracker (plain arrays: it may cross a pipe).

    Attributes:
        frame: the keyframe as tracked (rectified).
        T_world_cam: its tracked pose; frame_index: its index among the tracked frames.
        keyframe_id: its id; map_now: a mapping step follows it; first: the run's first frame.
        block_centres: every block the tracker has, ``(N, 3)`` (a block's id is its position).
        keyframe_poses: the tracker's keyframe poses when it was made, ``(K, 4, 4)`` (what the loop closer
            starts from; may be empty where the mapping side closes no loops).
        first_iterations: with ``first``, the map-only steps fitted before the update goes back (the rest of
            ``mapping.first_iterations`` runs in the background): what the tracker waits for.
    """

    frame: RgbdFrame
    T_world_cam: np.ndarray
    frame_index: int
    keyframe_id: int
    map_now: bool
    first: bool
    block_centres: np.ndarray
    keyframe_poses: np.ndarray
    first_iterations: int = 0


@dataclass
class Progress:
    """How far the mapping side is: keyframes ``integrated`` by the mapper and ``checked`` by the loop
    closer, loop corrections waiting for the mapper (``pending``), mapping steps and background chunks."""

    integrated: int = 0
    checked: int = 0
    pending: int = 0
    mapping_steps: int = 0
    background_chunks: int = 0


@dataclass
class _Work:
    """Background map iterations: ``iterations`` steps, poses optimised or not, keyframes up to
    ``fixed_until`` held."""

    kind: str
    iterations: int
    optimise_poses: bool
    fixed_until: int = 0


class MappingSide:
    """The mapper and loop-closer threads over ``block_map`` (the mapper's copy), or over ``backend``'s when
    one is given (a checkpoint's); messages to ``emit`` (module docstring). :meth:`close` ends both and
    returns the final map and keyframe store.

    With ``closes_loops`` false there is no loop thread (whatever ``cfg.loop`` says): corrections come from
    outside through :meth:`correct` (the ROS ``mapper`` node, whose loop closer is a node of its own).
    Another thread that reads the map or the keyframes while the side runs holds :attr:`map_lock`, which
    the mapper thread holds while it changes them."""

    def __init__(
        self,
        cfg: SlamConfig,
        block_map: BlockMap,
        emit: Emit,
        closes_loops: bool = True,
        backend: Backend | None = None,
    ):
        self.cfg = cfg
        self._emit_to = emit
        # the C++ kernels (and what imports them lazily) are loaded before the threads start, which would
        # otherwise race for a half-imported module
        _ext.prepare(cfg.grid_backend)
        # a backend restored from a checkpoint goes on with its map, keyframes and optimiser
        self.backend = Backend(cfg, block_map) if backend is None else backend
        #: what the tracker's copy of the tables holds, as the updates left it (which rows go next)
        self.mirror = map_update.ReceiverMirror(
            cfg.live.update_tolerance, cfg.live.update_float16, cfg.live.update_delta_step
        )
        self.loop_closer = LoopCloser(cfg.loop, seed=cfg.seed + 4) if cfg.loop.enabled and closes_loops else None
        self.map_lock = threading.RLock()
        # the loop thread adds keyframes to the closer's database while a lost tracker queries it
        self._database_lock = threading.Lock()
        self._cond = threading.Condition()
        self._stopping = False  # no more keyframes: the loop thread ends once its queue is empty ...
        self._mapper_stopping = False  # ... then the mapper, once it has integrated and corrected all
        self._to_mapper: deque[Handoff] = deque()
        self._to_loop: deque[Handoff] = deque()
        # (query keyframe id, loop start id, corrected poses by keyframe id, the correction's stamp or -1)
        self._corrections: list[tuple[int, int, np.ndarray, int]] = []
        self._loop_stamp = -1  # the newest stamped correction applied
        self._version = 0
        self._mapper_poses: np.ndarray | None = None  # its keyframe poses after its last step
        self.progress = Progress()
        self._mapper = threading.Thread(target=self._guard(self._map_loop, False), name="neb-slam-mapper", daemon=True)
        self._mapper.start()
        self._looper = None
        if self.loop_closer is not None:
            self._looper = threading.Thread(
                target=self._guard(self._loop_loop, True), name="neb-slam-loops", daemon=True
            )
            self._looper.start()

    # ------------------------------------------------------------------ the tracker's requests

    def submit(self, handoff: Handoff) -> None:
        """Queue a keyframe for the mapper (and the loop closer)."""
        with self._cond:
            self._to_mapper.append(handoff)
            if self.loop_closer is not None:
                self._to_loop.append(handoff)
            self._cond.notify_all()

    def correct(self, query_id: int, start_id: int, poses: np.ndarray, stamp_ns: int = -1) -> None:
        """Queue a loop correction of keyframes ``start_id + 1 .. query_id`` to ``poses[start_id + 1 :
        query_id + 1]`` (rows by keyframe id; the keyframes must have been submitted); ``stamp_ns`` names
        it in the updates' ``loop_stamp_ns`` once applied."""
        with self._cond:
            self._corrections.append((query_id, start_id, np.asarray(poses, dtype=np.float64), stamp_ns))
            self.progress.pending = len(self._corrections)
            self._cond.notify_all()

    def relocalise(self, frame: RgbdFrame, poses: np.ndarray) -> list[np.ndarray]:
        """Candidate poses of a lost frame from the keyframes the loop thread has added so far; ``poses``:
        the tracker's keyframe poses (it has every keyframe, the loop thread may lag)."""
        if self.loop_closer is None:
            return []
        with self._database_lock:
            return self.loop_closer.relocalise(frame, poses)

    def observed_points(self, seed: int, max_points: int) -> np.ndarray:
        """World points of the keyframes' kept pixels (mesh culling): :meth:`Backend.observed_points`."""
        with self.map_lock:
            return self.backend.observed_points(np.random.default_rng(seed), max_points)

    def memory(self) -> dict[str, int]:
        """Bytes of the mapping side's stores (:meth:`Backend.memory`) and of its queues (``queues``)."""
        from .memory import deep_bytes

        with self.map_lock, self._database_lock:
            stores = self.backend.memory(self.loop_closer)
        with self._cond:
            stores["queues"] = deep_bytes(list(self._to_mapper), list(self._to_loop), list(self._corrections))
        return stores

    def close(self, timeout_s: float) -> tuple[BlockMap, KeyframeStore]:
        """Let the loop thread check the queued keyframes and the mapper integrate them (and apply the
        corrections), stop both; background work that is left (the rest of a re-optimisation) is dropped."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._looper is not None:
            self._looper.join(max(0.0, deadline - time.monotonic()))
        with self._cond:
            self._mapper_stopping = True
            self._cond.notify_all()
        self._mapper.join(max(0.0, deadline - time.monotonic()))
        return self.backend.block_map, self.backend.keyframes

    # ------------------------------------------------------------------ messages

    def _tell(self, kind: str | None = None, payload: object = None) -> None:
        """Send a message (when ``kind`` is given) and the progress after it; called with the condition
        held, so that messages leave in the order the state changed."""
        if kind is not None:
            self._emit_to(kind, payload)
        self._emit_to("progress", replace(self.progress))

    # ------------------------------------------------------------------ mapping (its own thread)

    def _map_loop(self) -> None:
        background: list[_Work] = []
        unsent: set[int] = set()
        niced = False
        while True:
            with self._cond:
                self._cond.wait_for(
                    lambda background=background: (
                        self._mapper_stopping or self._to_mapper or self._corrections or background
                    )
                )
                if self._mapper_stopping and not self._to_mapper and not self._corrections:
                    return
                handoffs = list(self._to_mapper)
                self._to_mapper.clear()
                corrections, self._corrections = self._corrections, []
            with self.map_lock:
                self._cycle(handoffs, corrections, unsent, background)
            if not niced:
                # the first cycle (the first map, which the tracker waits for) ran at the tracker's priority
                lower_thread_priority(self.cfg.live.background_nice)
                niced = True

    def _cycle(self, handoffs: list[Handoff], corrections: list, unsent: set[int], background: list[_Work]) -> None:
        """One cycle of the mapper thread: integrate the queued keyframes, apply the corrections, one chunk
        of background work; each change goes back to the tracker."""
        changed: set[int] = set()
        if handoffs:
            changed |= self._integrate(handoffs, unsent, background)
            self.progress.mapping_steps += 1
        if corrections:  # their keyframes are integrated: handed to the mapper before the loop thread
            changed |= self._correct(corrections)
            background[:] = [w for w in background if w.kind != "loop"]
            start = corrections[-1][1]
            background += [
                _Work("loop", self.cfg.loop.map_iterations, False),
                _Work("loop", self.cfg.loop.joint_iterations, True, start),
            ]
        if background:
            # what this cycle integrated goes to the tracker first; then one chunk of the background work,
            # in every cycle, so that a steady stream of keyframes cannot hold the first map's refinement
            # (or a loop's re-optimisation) back for the whole run
            if changed or unsent:
                self._hand_back(changed | unsent)
                changed, unsent = set(), set()
            work = background[0]
            n = min(self.cfg.live.chunk_iterations, work.iterations)
            res = self.backend.mapper.optimise(n, optimise_poses=work.optimise_poses, fixed_until=work.fixed_until)
            changed |= res.changed_block_ids
            work.iterations -= n
            if work.iterations <= 0:
                background.pop(0)
            self.progress.background_chunks += 1
        self._hand_back(changed | unsent)
        unsent.clear()

    def _integrate(self, handoffs: list[Handoff], unsent: set[int], background: list[_Work]) -> set[int]:
        """Store the keyframes, create the blocks the tracker allocated, and map once for all of them."""
        bm, changed = self.backend.block_map, set()
        map_now = False
        for h in handoffs:
            for centre in h.block_centres[len(bm) :]:
                unsent.add(bm.add_block(torch.as_tensor(centre, dtype=torch.float32)).block_id)
            if h.first:
                n0 = min(h.first_iterations, self.cfg.mapping.first_iterations)
                # the tracker waits for this map: it is fitted on every core the process may use, whatever
                # thread count the mapping thread runs with otherwise
                torch.set_num_threads(usable_cores())
                try:
                    step = self.backend.add_keyframe(
                        h.frame, h.T_world_cam, h.frame_index, True, True, first_iterations=n0
                    )
                finally:
                    if self.cfg.live.torch_threads > 0:
                        torch.set_num_threads(self.cfg.live.torch_threads)
                changed |= step.changed_block_ids
                rest = self.cfg.mapping.first_iterations - n0
                if rest > 0:
                    background.append(_Work("first", rest, False))
            else:
                step = self.backend.add_keyframe(h.frame, h.T_world_cam, h.frame_index, False)
                changed |= step.changed_block_ids  # the blocks whose observed space grew
                map_now = map_now or h.map_now
        if map_now:
            changed |= self.backend.mapper.optimise().changed_block_ids
        return changed

    def _correct(self, corrections: list[tuple[int, int, np.ndarray, int]]) -> set[int]:
        """Move the keyframe poses by the loop corrections, in the order they came (each merged over the
        poses the previous ones left); the re-optimisation is left to the background work."""
        changed: set[int] = set()
        for query_id, start_id, poses, stamp_ns in corrections:
            kfs = self.backend.keyframes
            first = start_id + 1
            self._loop_stamp = max(self._loop_stamp, stamp_ns)
            if query_id < first:
                continue
            merged = merge_correction(kfs.poses(), first, poses[first : query_id + 1])
            changed |= self.backend.correct_loop(merged, start_id, reoptimise=False).changed_block_ids
        return changed

    def _hand_back(self, block_ids: set[int]) -> None:
        kfs = self.backend.keyframes
        poses = kfs.poses() if len(kfs) else np.zeros((0, 4, 4))
        stamps = np.array([kf.stamp_ns for kf in kfs.keyframes], dtype=np.int64)
        update = map_update.capture(
            self.backend.block_map,
            block_ids,
            self._version + 1,
            int(stamps[-1]) if len(stamps) else -1,  # the newest keyframe integrated
            stamps,
            poses,
            self._loop_stamp,
            mirror=self.mirror,
        )
        with self._cond:
            self._version += 1
            self._mapper_poses = poses
            self.progress.integrated = len(kfs)
            self.progress.pending = len(self._corrections)
            self._tell("update", update)
            self._cond.notify_all()

    # ------------------------------------------------------------------ loop closure (its own thread)

    def _loop_loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._stopping or self._to_loop)
                if not self._to_loop:
                    return
                *behind, h = self._to_loop
                self._to_loop.clear()
                refined = self._mapper_poses
            # keyframes that queued up while the closer was busy go into its database (later loops and
            # relocalisation find them); only the newest is checked, so the queue, and the frames it
            # holds, stay bounded however fast keyframes come
            for old in behind:
                with self._database_lock:
                    self.loop_closer.add_keyframe(old.keyframe_id, old.frame)
            kid = h.keyframe_id
            poses = h.keyframe_poses.copy()
            if refined is not None:  # the mapper's poses where it has them, the tracker's after
                poses[: min(len(refined), len(poses))] = refined[: len(poses)]
            try:
                with self._database_lock:
                    self.loop_closer.add_keyframe(kid, h.frame)
                event, corrected = self.loop_closer.close(kid, poses, h.frame)
            except Exception as exc:  # one keyframe's failed check must not end loop closure for good
                log.warning("loop check of keyframe %d failed (%s: %s); skipped", kid, type(exc).__name__, exc)
                event, corrected = None, None
            with self._cond:
                self.progress.checked = kid + 1
                if event is not None and event.applied:
                    self._corrections.append((kid, event.start_id, corrected, -1))
                    self.progress.pending = len(self._corrections)
                    self._cond.notify_all()
                self._tell(None if event is None else "loop", event)

    # ------------------------------------------------------------------ threads

    def _guard(self, target, nice: bool):
        def run():
            if self.cfg.live.torch_threads > 0:
                # OpenMP's thread count is per thread: a new thread starts from the process default
                torch.set_num_threads(self.cfg.live.torch_threads)
            if nice:  # the tracker goes first
                lower_thread_priority(self.cfg.live.background_nice)
            try:
                target()
            except Exception as exc:  # reported to the tracker; the other thread goes on
                with self._cond:
                    self._tell("error", f"{threading.current_thread().name}: {type(exc).__name__}: {exc}")
                    self._cond.notify_all()

        return run


# ---------------------------------------------------------------------- the child process


def _to_bytes(obj) -> bytes:
    # torch's own serialisation: tensors as bytes in the message (a pickled tensor would go through
    # shared-memory handles, one file descriptor per storage)
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def _from_bytes(data: bytes):
    return torch.load(io.BytesIO(data), weights_only=False)


class ProcessMapping:
    """The mapping side in a child process (module docstring). The constructor starts the child and
    waits until it has imported the engine (seconds); :meth:`begin` hands it the configuration and the map
    and connects the messages to ``emit`` (called from a reader thread of this process).

    A process that may construct its live engine late (a ROS node, at its first frame) starts this
    early, so that the import is not the first frame's wait."""

    def __init__(self, start_timeout_s: float = 120.0):
        ctx = multiprocessing.get_context("spawn")
        self._conn, child_conn = ctx.Pipe()
        self._process = ctx.Process(target=_serve, args=(child_conn,), name="neb-slam-mapping", daemon=True)
        self._process.start()
        child_conn.close()
        if not self._conn.poll(start_timeout_s):
            self._process.kill()
            raise RuntimeError(f"the mapping process did not start within {start_timeout_s:g} s")
        kind, payload = self._conn.recv()
        if kind != "ready":
            raise RuntimeError(f"the mapping process failed to start: {payload}")
        self._send_lock = threading.Lock()
        self._cond = threading.Condition()
        self._replies: dict[int, object] = {}
        self._calls = 0
        self._final: bytes | None = None
        self._gone: str | None = None
        self._emit: Emit | None = None
        self._reader: threading.Thread | None = None

    def begin(self, cfg: SlamConfig, block_map: BlockMap, emit: Emit) -> None:
        self._emit = emit
        self._send(("begin", (cfg, _to_bytes(block_map))))
        self._reader = threading.Thread(target=self._read, name="neb-slam-mapping-reader", daemon=True)
        self._reader.start()

    def _send(self, message) -> None:
        with self._send_lock:
            self._conn.send(message)

    def _read(self) -> None:
        while True:
            try:
                kind, payload = self._conn.recv()
            except (EOFError, OSError):
                self._process.join(5.0)
                with self._cond:
                    if self._final is None:
                        self._gone = f"the mapping process ended (exit code {self._process.exitcode})"
                        self._emit("error", self._gone)
                    self._cond.notify_all()
                return
            if kind == "reply":
                with self._cond:
                    self._replies[payload[0]] = payload[1]
                    self._cond.notify_all()
            elif kind == "final":
                with self._cond:
                    self._final = payload
                    self._cond.notify_all()
            else:
                self._emit(kind, payload)

    def _call(self, name: str, *args):
        with self._cond:
            self._calls += 1
            call_id = self._calls
        self._send(("call", (call_id, name, args)))
        with self._cond:
            self._cond.wait_for(lambda: call_id in self._replies or self._gone is not None)
            if call_id not in self._replies:
                raise RuntimeError(self._gone)
            value = self._replies.pop(call_id)
        if isinstance(value, BaseException):
            raise value
        return value

    def submit(self, handoff: Handoff) -> None:
        self._send(("handoff", handoff))

    def relocalise(self, frame: RgbdFrame, poses: np.ndarray) -> list[np.ndarray]:
        return self._call("relocalise", frame, poses)

    def observed_points(self, seed: int, max_points: int) -> np.ndarray:
        return self._call("observed_points", seed, max_points)

    def memory(self) -> dict[str, int]:
        return self._call("memory")

    @property
    def pid(self) -> int | None:
        """The mapping process's id."""
        return self._process.pid

    def close(self, timeout_s: float) -> tuple[BlockMap, KeyframeStore]:
        """Close the mapping side in the child (as :meth:`MappingSide.close`), take its final map and
        keyframes, and end the child."""
        try:
            self._send(("close", timeout_s))
        except (BrokenPipeError, OSError) as exc:
            raise RuntimeError(f"the mapping process is gone: {self._gone or exc}") from exc
        with self._cond:
            self._cond.wait_for(lambda: self._final is not None or self._gone is not None, timeout_s + 60.0)
            final = self._final
        self._process.join(30.0)
        if self._process.is_alive():
            self._process.kill()
        if self._reader is not None:
            self._reader.join(5.0)
        if final is None:
            raise RuntimeError(self._gone or f"the mapping process sent no final map within {timeout_s:g} s")
        return _from_bytes(final)

    def shutdown(self) -> None:
        """End the child without its final map (a process that never began a run)."""
        if self._process.is_alive():
            self._process.kill()
        self._process.join(5.0)


def _serve(conn) -> None:
    """The child process: prepare the engine, then run one :class:`MappingSide` with the messages of the
    pipe ``conn`` (``begin``, ``handoff``, ``call``, ``close``).

    Ctrl-C reaches every process of the terminal's group, and a service manager's SIGTERM every process
    of the service: the child ignores both, because its parent, which handles them, still needs it to
    finish the queued keyframes and hand over the final map. A parent that dies closes the pipe, which
    ends the child."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        prepare_engine_process()
    except Exception as exc:
        conn.send(("failed", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", None))
    send_lock = threading.Lock()

    def emit(kind: str, payload: object) -> None:
        with send_lock:
            conn.send((kind, payload))

    side: MappingSide | None = None
    while True:
        try:
            kind, payload = conn.recv()
        except (EOFError, OSError):  # the tracker's process is gone
            return
        if kind == "begin":
            cfg, map_bytes = payload
            torch.manual_seed(cfg.seed)  # as the tracker's process seeds before a mapping side of its own
            side = MappingSide(cfg, _from_bytes(map_bytes), emit)
        elif kind == "handoff":
            side.submit(payload)
        elif kind == "call":
            call_id, name, args = payload
            try:
                value = getattr(side, name)(*args)
            except Exception as exc:
                value = RuntimeError(f"{name} in the mapping process: {type(exc).__name__}: {exc}")
            emit("reply", (call_id, value))
        elif kind == "close":
            final = side.close(payload)
            emit("final", _to_bytes(final))
            return
