"""The engine for a camera that does not wait: tracking never waits for mapping or loop closure.

    slam = LiveSlam(config, T_world_first)
    for frame in camera:                 # the newest frame whenever the engine is free
        result = slam.process(frame)     # tracking only: the pose of this frame, now
    slam.close()                         # finish the queued keyframes, stop the threads
    trajectory = slam.trajectory()

Three threads share the work, each with its own state:

- the caller's thread tracks (:class:`~neb_slam_core.slam.Frontend`) against the tracker's copy of the
  map, allocates blocks and hands keyframes on;
- the mapping thread (:class:`~neb_slam_core.slam.Backend`) integrates keyframes into its own copy of the
  map, optimises it, and after every step hands back a map update (the blocks it changed, the
  decoders, the keyframe poses: :class:`~neb_slam_core.scene.map_update.MapUpdate`, copied in memory),
  which the tracker applies before its next frame;
- the loop thread (:class:`~neb_slam_core.loop.closer.LoopCloser`) checks every keyframe for a loop and
  hands applied corrections to the mapping thread.

It is the protocol of the ROS ``tracker`` / ``mapper`` / ``loop_closer`` nodes, in one process without
serialisation. Three rules keep the camera from waiting:

- the first frame's map is fitted with ``live.first_iterations`` map-only steps, on every core the
  process may use, before the second frame is tracked; the rest of ``mapping.first_iterations`` runs in the
  background, one chunk of ``live.chunk_iterations`` after each batch of keyframes (and while no
  keyframe waits), so a steady stream of keyframes does not hold it back;
- keyframes that queued up while the mapper was busy are integrated together, with one mapping step for
  all of them, so the mapping lag stays bounded by one step's worth of keyframes;
- a loop correction moves the keyframe poses at once; its two-stage re-optimisation runs in chunks of
  ``live.chunk_iterations`` in the same way, and a correction that arrives while one is being worked
  off replaces what is left of it.

The order of events depends on the machine's speed, so a run is not reproducible to the bit; the
deterministic engine is :class:`~neb_slam_core.slam.Slam`.

Threads: ``live.torch_threads`` (the ``live`` preset: 1) sets torch's intra-op threads in each of the
three threads, so that on two cores the tracker and the mapper each keep one busy, and the mapping and
loop threads run ``live.background_nice`` nicer than the tracker, so that the tracker keeps its core
when the loop thread wants one too.
"""

from __future__ import annotations

import copy
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import torch

from .config import SlamConfig
from .engine_process import lower_thread_priority, usable_cores
from .io.trajectory import Trajectory
from .loop.closer import LoopCloser
from .loop.correction import merge_correction
from .mapping.keyframes import KeyframeStore
from .scene import _ext, map_update
from .scene.block_map import BlockMap
from .slam import Backend, Frontend, FrontendStep, new_block_map
from .types import LoopEvent, RgbdFrame, StepResult


@dataclass
class _Handoff:
    """A keyframe on its way from the tracker: the step, every block the tracker has (ids are positions)
    and the tracker's keyframe poses when it was made."""

    step: FrontendStep
    block_centres: np.ndarray
    keyframe_poses: np.ndarray


@dataclass
class _Work:
    """Background map iterations: ``iterations`` steps, poses optimised or not, keyframes up to
    ``fixed_until`` held."""

    kind: str
    iterations: int
    optimise_poses: bool
    fixed_until: int = 0


@dataclass
class LiveStats:
    """How the threads kept up.

    Attributes:
        mapping_lag: keyframes handed to the mapper and not integrated yet (now).
        mapping_lag_max: the largest lag seen when a frame was tracked.
        map_updates: map updates the tracker applied.
        mapping_steps: mapping steps for new keyframes; background_chunks: chunks of background work.
        first_map_wait_s: how long the second frame waited for the first map.
    """

    mapping_lag: int = 0
    mapping_lag_max: int = 0
    map_updates: int = 0
    mapping_steps: int = 0
    background_chunks: int = 0
    first_map_wait_s: float = 0.0
    lag_history: list[int] = field(default_factory=list)


class LiveSlam:
    """Tracking in the caller's thread, mapping and loop closure in threads of their own (see the module
    docstring). The interface of :class:`~neb_slam_core.slam.Slam` for what a run directory needs."""

    def __init__(self, cfg: SlamConfig, T_world_first: np.ndarray | None = None, block_map: BlockMap | None = None):
        self.cfg = cfg
        # the caller's thread tracks with live.torch_threads until close() gives it back its own count
        self._caller_threads = torch.get_num_threads()
        if cfg.live.torch_threads > 0:
            torch.set_num_threads(cfg.live.torch_threads)
        # the C++ kernels (and what imports them lazily) are loaded before the threads start, which would
        # otherwise race for a half-imported module
        _ext.prepare(cfg.grid_backend)
        torch.manual_seed(cfg.seed)
        mapper_map = new_block_map(cfg) if block_map is None else block_map
        self._track_map = copy.deepcopy(mapper_map)
        self.frontend = Frontend(cfg, self._track_map, T_world_first, own_map=True)
        self.backend = Backend(cfg, mapper_map)
        self.loop_closer = LoopCloser(cfg.loop, seed=cfg.seed + 4) if cfg.loop.enabled else None
        # the loop thread adds keyframes to the closer's database while a lost tracker queries it
        self._database_lock = threading.Lock()
        if self.loop_closer is not None:
            self.frontend.relocaliser = self._relocalisation_poses
        self.loops: list[LoopEvent] = []
        self.stats = LiveStats()
        self.errors: list[str] = []

        self._cond = threading.Condition()
        self._stopping = False  # no more keyframes: the loop thread ends once its queue is empty ...
        self._mapper_stopping = False  # ... then the mapper, once it has integrated and corrected all
        self._to_mapper: deque[_Handoff] = deque()
        self._to_loop: deque[_Handoff] = deque()
        self._corrections: list[tuple[int, int, np.ndarray]] = []  # (keyframe id, loop start id, poses)
        self._updates: list[map_update.MapUpdate] = []
        self._version = 0
        self._integrated = 0  # keyframes the mapper has integrated
        self._mapper_poses: np.ndarray | None = None  # its keyframe poses after its last step
        self._loaded_map = block_map is not None
        self._mapper = threading.Thread(target=self._guard(self._map_loop), name="neb-slam-mapper", daemon=True)
        self._mapper.start()
        self._looper = None
        if self.loop_closer is not None:
            self._looper = threading.Thread(target=self._guard(self._loop_loop), name="neb-slam-loops", daemon=True)
            self._looper.start()

    # ------------------------------------------------------------------ state (a Slam's interface)

    @property
    def block_map(self) -> BlockMap:
        """The mapper's map: the most refined one (read it after :meth:`close`)."""
        return self.backend.block_map

    @property
    def keyframes(self) -> KeyframeStore:
        return self.backend.keyframes

    @property
    def n_frames(self) -> int:
        return self.frontend.n_frames

    def pose_of(self, i: int) -> np.ndarray:
        return self.frontend.pose_of(i)

    def trajectory(self) -> Trajectory:
        """Poses of every tracked frame, with the newest keyframe poses the tracker has received."""
        return self.frontend.trajectory()

    def observed_points(self, max_points: int = 2_000_000) -> np.ndarray:
        return self.backend.observed_points(self.frontend.rng, max_points)

    # ------------------------------------------------------------------ tracking (the caller's thread)

    def process(self, frame: RgbdFrame) -> StepResult:
        """Track ``frame`` against the newest map the mapper handed back; hand a keyframe on. Waits only
        for the first map (before the second frame of a run that started from an empty map)."""
        t_start = time.perf_counter()
        if self.errors:
            raise RuntimeError(f"the live engine's background work failed: {self.errors[0]}")
        self.wait_for_map()
        self._apply_updates()
        step = self.frontend.step(frame)
        if step.keyframe_id is not None:
            handoff = _Handoff(
                step,
                self._track_map.centres().detach().cpu().double().numpy().reshape(-1, 3),
                np.stack(self.frontend.keyframe_poses),
            )
            with self._cond:
                self._to_mapper.append(handoff)
                if self.loop_closer is not None:
                    self._to_loop.append(handoff)
                self._cond.notify_all()
        with self._cond:
            lag = len(self.frontend.keyframe_poses) - self._integrated
        self.stats.mapping_lag = lag
        self.stats.mapping_lag_max = max(self.stats.mapping_lag_max, lag)
        self.stats.lag_history.append(lag)
        result = step.result
        result.timings.total_ms = 1e3 * (time.perf_counter() - t_start)
        return result

    def _relocalisation_poses(self, frame: RgbdFrame) -> list[np.ndarray]:
        """Candidate poses of a lost frame from the keyframes the loop thread has added so far (the
        tracker's keyframe poses: it has every keyframe, the loop thread may lag)."""
        poses = np.stack(self.frontend.keyframe_poses)
        with self._database_lock:
            return self.loop_closer.relocalise(frame, poses)

    def wait_for_map(self) -> None:
        """After the first frame of a run from an empty map: wait until the mapper has fitted the first map
        (``live.first_iterations`` steps), the only wait of the tracker. A caller that picks the newest
        frame calls it before picking, so that the frame it tracks is not one that waited."""
        if self.frontend.n_frames != 1 or self._loaded_map or self._version > 0:
            return
        t0 = time.perf_counter()
        with self._cond:
            self._cond.wait_for(lambda: self._version > 0 or self._stopping or self.errors)
        self.stats.first_map_wait_s += time.perf_counter() - t0

    def next_frame(self, stamps_ns) -> int:
        """Which of the arrived frames (``stamps_ns``) to track next: :meth:`Frontend.next_frame`."""
        return self.frontend.next_frame(stamps_ns)

    def wait_integrated(self, timeout_s: float | None = None) -> bool:
        """Wait until the mapper has integrated every keyframe handed to it and applied every loop
        correction that came (background refinement may go on); False on timeout or a failed thread.
        Not for a live camera: it makes the caller as slow as mapping (tests, replays that want it)."""
        with self._cond:
            done = self._cond.wait_for(
                lambda: (
                    self.errors
                    or (
                        not self._to_mapper
                        and not self._corrections
                        and not self._to_loop
                        and self._integrated == len(self.frontend.keyframe_poses)
                    )
                ),
                timeout_s,
            )
        return bool(done) and not self.errors

    def _apply_updates(self) -> None:
        with self._cond:
            updates, self._updates = self._updates, []
        for update in updates:
            map_update.apply(update, self._track_map)
            if len(update.keyframe_poses):
                self.frontend.set_keyframe_poses(update.keyframe_poses)
            self.stats.map_updates += 1

    # ------------------------------------------------------------------ mapping (its own thread)

    def _map_loop(self) -> None:
        live = self.cfg.live
        background: list[_Work] = []
        unsent: set[int] = set()
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
            changed: set[int] = set()
            if handoffs:
                changed |= self._integrate(handoffs, unsent, background)
                self.stats.mapping_steps += 1
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
                n = min(live.chunk_iterations, work.iterations)
                res = self.backend.mapper.optimise(n, optimise_poses=work.optimise_poses, fixed_until=work.fixed_until)
                changed |= res.changed_block_ids
                work.iterations -= n
                if work.iterations <= 0:
                    background.pop(0)
                self.stats.background_chunks += 1
            self._hand_back(changed | unsent)
            unsent.clear()

    def _integrate(self, handoffs: list[_Handoff], unsent: set[int], background: list[_Work]) -> set[int]:
        """Store the keyframes, create the blocks the tracker allocated, and map once for all of them."""
        bm, changed = self.backend.block_map, set()
        map_now = False
        for h in handoffs:
            for centre in h.block_centres[len(bm) :]:
                unsent.add(bm.add_block(torch.as_tensor(centre, dtype=torch.float32)).block_id)
            s = h.step
            if s.first:
                n0 = min(self.cfg.live.first_iterations, self.cfg.mapping.first_iterations)
                # the tracker waits for this map (wait_for_map): it is fitted on every core the process may
                # use, whatever thread count the caller (a ROS node's worker: live.torch_threads) runs with
                torch.set_num_threads(usable_cores())
                try:
                    step = self.backend.add_keyframe(
                        s.frame, s.result.T_world_cam, s.result.frame_index, True, True, first_iterations=n0
                    )
                finally:
                    if self.cfg.live.torch_threads > 0:
                        torch.set_num_threads(self.cfg.live.torch_threads)
                changed |= step.changed_block_ids
                rest = self.cfg.mapping.first_iterations - n0
                if rest > 0:
                    background.append(_Work("first", rest, False))
            else:
                step = self.backend.add_keyframe(s.frame, s.result.T_world_cam, s.result.frame_index, False)
                changed |= step.changed_block_ids  # the blocks whose observed space grew
                map_now = map_now or s.map_now
        if map_now:
            changed |= self.backend.mapper.optimise().changed_block_ids
        return changed

    def _correct(self, corrections: list[tuple[int, int, np.ndarray]]) -> set[int]:
        """Move the keyframe poses by the loop corrections, in the order they came (each merged over the
        poses the previous ones left); the re-optimisation is left to the background work."""
        changed: set[int] = set()
        for query_id, start_id, poses in corrections:
            kfs = self.backend.keyframes
            first = start_id + 1
            if query_id < first:
                continue
            merged = merge_correction(kfs.poses(), first, poses[first : query_id + 1])
            changed |= self.backend.correct_loop(merged, start_id, reoptimise=False).changed_block_ids
        return changed

    def _hand_back(self, block_ids: set[int]) -> None:
        kfs = self.backend.keyframes
        poses = kfs.poses() if len(kfs) else np.zeros((0, 4, 4))
        update = snapshot(
            self.backend.block_map,
            block_ids,
            self._version + 1,
            poses,
            np.array([kf.stamp_ns for kf in kfs.keyframes], dtype=np.int64),
        )
        with self._cond:
            self._version += 1
            self._updates.append(update)
            self._integrated = len(kfs)
            self._mapper_poses = poses
            self._cond.notify_all()

    # ------------------------------------------------------------------ loop closure (its own thread)

    def _loop_loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._stopping or self._to_loop)
                if not self._to_loop:
                    return
                h = self._to_loop.popleft()
                refined = self._mapper_poses
            kid = h.step.keyframe_id
            poses = h.keyframe_poses.copy()
            if refined is not None:  # the mapper's poses where it has them, the tracker's after
                poses[: min(len(refined), len(poses))] = refined[: len(poses)]
            with self._database_lock:
                self.loop_closer.add_keyframe(kid, h.step.frame)
            event, corrected = self.loop_closer.close(kid, poses, h.step.frame)
            if event is None:
                continue
            with self._cond:
                self.loops.append(event)
                if event.applied:
                    self._corrections.append((kid, event.start_id, corrected))
                    self._cond.notify_all()

    def live_metrics(self, frames_in: int, span_s: float) -> dict:
        """The live figures of a run for its metrics.json: ``frames_in`` frames reached the engine's input
        (those it did not track count as dropped), over ``span_s`` seconds from the first frame's arrival
        to the last tracked frame."""
        st = self.stats
        return {
            "live": True,
            "frames_in": frames_in,
            "frames_tracked": self.n_frames,
            "frames_dropped": frames_in - self.n_frames,
            "tracked_fps": self.n_frames / max(span_s, 1e-9),
            "live_span_s": span_s,
            "mapping_lag_end": st.mapping_lag,
            "mapping_lag_max": st.mapping_lag_max,
            "mapping_lag_history": list(st.lag_history),
            "map_updates": st.map_updates,
            "mapping_steps": st.mapping_steps,
            "background_chunks": st.background_chunks,
            "first_map_wait_s": st.first_map_wait_s,
            "engine_errors": list(self.errors),
        }

    # ------------------------------------------------------------------ shutdown

    def _guard(self, target):
        def run():
            if self.cfg.live.torch_threads > 0:
                # OpenMP's thread count is per thread: a new thread starts from the process default
                torch.set_num_threads(self.cfg.live.torch_threads)
            lower_thread_priority(self.cfg.live.background_nice)  # the caller's thread tracks: it goes first
            try:
                target()
            except Exception as exc:  # reported by close() and the next process(); the tracker goes on
                with self._cond:
                    self.errors.append(f"{threading.current_thread().name}: {type(exc).__name__}: {exc}")
                    self._cond.notify_all()

        return run

    def close(self, timeout_s: float = 600.0) -> None:
        """Let the loop thread check the queued keyframes and the mapper integrate them (and apply the
        corrections), stop both, and give the tracker the final keyframe poses. Background work that is
        left (the rest of a re-optimisation) is dropped."""
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
        self._apply_updates()
        with self._cond:
            self.stats.mapping_lag = len(self.frontend.keyframe_poses) - self._integrated
        torch.set_num_threads(self._caller_threads)


def snapshot(
    block_map: BlockMap, block_ids, version: int, keyframe_poses: np.ndarray, keyframe_stamps_ns: np.ndarray
) -> map_update.MapUpdate:
    """A :class:`~neb_slam_core.scene.map_update.MapUpdate` of ``block_map`` in memory: copies of the tables
    and observed-space records of ``block_ids``, of the decoders and of the keyframe poses, for another
    thread to apply."""
    blocks = []
    for i in sorted(int(b) for b in block_ids):
        block = block_map.blocks[i]
        blocks.append(
            map_update.BlockState(
                i,
                block.centre.detach().cpu().numpy().copy(),
                block.grid.table.detach().cpu().reshape(-1).clone().numpy(),
                map_update.pack_observed(block.observed),
            )
        )
    decoders = torch.nn.utils.parameters_to_vector(block_map.decoders.parameters()).detach().cpu().clone().numpy()
    return map_update.MapUpdate(
        version,
        -1,
        blocks,
        decoders,
        np.asarray(keyframe_stamps_ns, dtype=np.int64),
        np.array(keyframe_poses, dtype=np.float64),
    )
