"""The engine for a camera that does not wait: tracking never waits for mapping or loop closure.

    slam = LiveSlam(config, T_world_first)
    for frame in camera:                 # the newest frame whenever the engine is free
        result = slam.process(frame)     # tracking only: the pose of this frame, now
    slam.close()                         # finish the queued keyframes, stop the mapping side
    trajectory = slam.trajectory()

The caller's thread tracks (:class:`~neb_slam_core.slam.Frontend`) against the tracker's copy of the map,
allocates blocks and hands keyframes to the mapping side (:mod:`neb_slam_core.live_mapping`): the mapper
integrates them into its own copy of the map, optimises it, and after every step hands back a map update
(the blocks it changed, the decoders, the keyframe poses:
:class:`~neb_slam_core.scene.map_update.MapUpdate`), which the tracker applies before its next frame; the
loop closer checks every keyframe for a loop and hands applied corrections to the mapper. The mapping
side runs in a process of its own (``live.mapping_process``, the default: the tracker and the mapper
then each keep a core, see :mod:`neb_slam_core.live_mapping`) or in threads of this one.

It is the protocol of the ROS ``tracker`` / ``mapper`` / ``loop_closer`` nodes, without their topics. The
tracker waits only once: after the first frame, for the first map (``live.first_iterations`` steps).

The order of events depends on the machine's speed, so a run is not reproducible to the bit; the
deterministic engine is :class:`~neb_slam_core.slam.Slam`.

Threads: ``live.torch_threads`` (the ``live`` preset: 1) sets torch's intra-op threads of the tracker and
of each mapping-side thread, so that on two cores the tracker and the mapper each keep one busy; the
mapping side runs ``live.background_nice`` nicer than the tracker, so that the tracker keeps its core
when everything wants one.
"""

from __future__ import annotations

import copy
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from .config import SlamConfig
from .io.trajectory import Trajectory
from .live_mapping import Handoff, MappingSide, ProcessMapping, Progress
from .mapping.keyframes import KeyframeStore
from .scene import map_update
from .scene.block_map import BlockMap
from .slam import Frontend, keyframe_points, new_block_map
from .types import LoopEvent, RgbdFrame, StepResult


@dataclass
class LiveStats:
    """How the mapping side kept up.

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
    """Tracking in the caller's thread, mapping and loop closure beside it (see the module docstring). The
    interface of :class:`~neb_slam_core.slam.Slam` for what a run directory needs.

    ``mapping``: a :class:`~neb_slam_core.live_mapping.ProcessMapping` started earlier (by a process that
    constructs the engine at its first frame); by default one is started here when
    ``live.mapping_process`` is set."""

    def __init__(
        self,
        cfg: SlamConfig,
        T_world_first: np.ndarray | None = None,
        block_map: BlockMap | None = None,
        mapping: ProcessMapping | None = None,
    ):
        self.cfg = cfg
        # the caller's thread tracks with live.torch_threads until close() gives it back its own count
        self._caller_threads = torch.get_num_threads()
        if cfg.live.torch_threads > 0:
            torch.set_num_threads(cfg.live.torch_threads)
        torch.manual_seed(cfg.seed)
        mapper_map = new_block_map(cfg) if block_map is None else block_map
        if mapping is None and cfg.live.mapping_process:
            mapping = ProcessMapping()
        # a mapping process gets its own copy with the map's bytes; threads here need one made
        self._track_map = mapper_map if mapping is not None else copy.deepcopy(mapper_map)
        self.frontend = Frontend(cfg, self._track_map, T_world_first, own_map=True)
        self.loops: list[LoopEvent] = []
        self.stats = LiveStats()
        self.errors: list[str] = []
        self._cond = threading.Condition()
        self._updates: list[map_update.MapUpdate] = []
        self._version = 0
        self._progress = Progress()
        self._revisions: dict[int, int] = {}  # per block, the map updates that carried it
        self._final: tuple[BlockMap, KeyframeStore] | None = None
        self._loaded_map = block_map is not None
        if mapping is not None:
            mapping.begin(cfg, mapper_map, self._receive)
            self._mapping = mapping
        else:
            self._mapping = MappingSide(cfg, mapper_map, self._receive)
        if cfg.loop.enabled:
            self.frontend.relocaliser = self._relocalisation_poses

    # ------------------------------------------------------------------ state (a Slam's interface)

    @property
    def block_map(self) -> BlockMap:
        """The map: the tracker's copy (the mapper's as of its last update) while the engine runs, the
        mapper's after :meth:`close`."""
        return self._track_map if self._final is None else self._final[0]

    @property
    def keyframes(self) -> KeyframeStore:
        """The mapper's keyframe store (after :meth:`close`)."""
        if self._final is None:
            raise RuntimeError("the live engine's keyframe store is the mapper's: read it after close()")
        return self._final[1]

    @property
    def block_revisions(self) -> dict[int, int]:
        """Per block id, how many map updates changed it (what a mesh re-extracts by)."""
        return self._revisions

    @property
    def n_frames(self) -> int:
        return self.frontend.n_frames

    def pose_of(self, i: int) -> np.ndarray:
        return self.frontend.pose_of(i)

    def trajectory(self) -> Trajectory:
        """Poses of every tracked frame, with the newest keyframe poses the tracker has received."""
        return self.frontend.trajectory()

    def observed_points(self, max_points: int = 2_000_000) -> np.ndarray:
        """World points of the keyframes' kept pixels (mesh culling), from the mapper's keyframes."""
        if self._final is not None:
            return keyframe_points(self._final[1], self.frontend.rng, max_points)
        return self._mapping.observed_points(self.cfg.seed, max_points)

    def memory(self) -> dict[str, int]:
        """Bytes held by each store of the engine (:func:`~neb_slam_core.memory.deep_bytes`): the mapping
        side's (:meth:`~neb_slam_core.live_mapping.MappingSide.memory`, in its process when it has one),
        ``frames`` (:meth:`Frontend.memory`), ``tracker_map`` (the tracker's copy of the map) and
        ``loops``."""
        from .memory import deep_bytes

        stores = self._mapping.memory() if self._final is None else {}
        stores.update(
            frames=self.frontend.memory(), tracker_map=deep_bytes(self._track_map), loops=deep_bytes(self.loops)
        )
        return stores

    @property
    def mapping_pid(self) -> int | None:
        """The id of the mapping side's process (None: it runs in threads of this one)."""
        return self._mapping.pid if isinstance(self._mapping, ProcessMapping) else None

    # ------------------------------------------------------------------ tracking (the caller's thread)

    def process(self, frame: RgbdFrame) -> StepResult:
        """Track ``frame`` against the newest map the mapper handed back; hand a keyframe on. Waits only
        for the first map (before the second frame of a run that started from an empty map)."""
        t_start = time.perf_counter()
        if self.errors:
            raise RuntimeError(f"the live engine's mapping side failed: {self.errors[0]}")
        self.wait_for_map()
        self._apply_updates()
        step = self.frontend.step(frame)
        if step.keyframe_id is not None:
            self._mapping.submit(
                Handoff(
                    step.frame,
                    step.result.T_world_cam,
                    step.result.frame_index,
                    step.keyframe_id,
                    step.map_now,
                    step.first,
                    self._track_map.centres().detach().cpu().double().numpy().reshape(-1, 3),
                    np.stack(self.frontend.keyframe_poses),
                    self.cfg.live.first_iterations,
                )
            )
        with self._cond:
            lag = len(self.frontend.keyframe_poses) - self._progress.integrated
        self.stats.mapping_lag = lag
        self.stats.mapping_lag_max = max(self.stats.mapping_lag_max, lag)
        self.stats.lag_history.append(lag)
        result = step.result
        result.timings.total_ms = 1e3 * (time.perf_counter() - t_start)
        return result

    def _relocalisation_poses(self, frame: RgbdFrame) -> list[np.ndarray]:
        """Candidate poses of a lost frame from the loop closer's keyframe database."""
        return self._mapping.relocalise(frame, np.stack(self.frontend.keyframe_poses))

    def _receive(self, kind: str, payload: object) -> None:
        """A message of the mapping side (:mod:`neb_slam_core.live_mapping`), from one of its threads."""
        with self._cond:
            if kind == "update":
                self._updates.append(payload)
                self._version += 1
            elif kind == "progress":
                self._progress = payload
                self.stats.mapping_steps = payload.mapping_steps
                self.stats.background_chunks = payload.background_chunks
            elif kind == "loop":
                self.loops.append(payload)
            elif kind == "error":
                self.errors.append(str(payload))
            self._cond.notify_all()

    def wait_for_map(self) -> None:
        """After the first frame of a run from an empty map: wait until the mapper has fitted the first map
        (``live.first_iterations`` steps), the only wait of the tracker. A caller that picks the newest
        frame calls it before picking, so that the frame it tracks is not one that waited."""
        if self.frontend.n_frames != 1 or self._loaded_map or self._version > 0:
            return
        t0 = time.perf_counter()
        with self._cond:
            self._cond.wait_for(lambda: self._version > 0 or self.errors)
        self.stats.first_map_wait_s += time.perf_counter() - t0

    def next_frame(self, stamps_ns) -> int:
        """Which of the arrived frames (``stamps_ns``) to track next: :meth:`Frontend.next_frame`."""
        return self.frontend.next_frame(stamps_ns)

    def wait_integrated(self, timeout_s: float | None = None) -> bool:
        """Wait until the mapper has integrated every keyframe handed to it, the loop closer has checked
        them and every correction that came is applied (background refinement may go on); False on timeout
        or a failure of the mapping side. Not for a live camera: it makes the caller as slow as mapping
        (tests, replays that want it)."""
        n = len(self.frontend.keyframe_poses)
        checked = n if self.cfg.loop.enabled else 0

        def done() -> bool:
            p = self._progress
            return p.integrated == n and p.checked >= checked and p.pending == 0

        with self._cond:
            ok = self._cond.wait_for(lambda: self.errors or done(), timeout_s)
        return bool(ok) and not self.errors

    def _apply_updates(self) -> None:
        with self._cond:
            updates, self._updates = self._updates, []
        for update in updates:
            map_update.apply(update, self._track_map)
            for b in update.block_ids:
                self._revisions[b] = self._revisions.get(b, 0) + 1
            if len(update.keyframe_poses):
                self.frontend.set_keyframe_poses(update.keyframe_poses)
            self.stats.map_updates += 1

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
            "mapping_process": isinstance(self._mapping, ProcessMapping),
            "engine_errors": list(self.errors),
        }

    # ------------------------------------------------------------------ shutdown

    def close(self, timeout_s: float = 600.0) -> None:
        """Let the loop closer check the queued keyframes and the mapper integrate them (and apply the
        corrections), stop the mapping side, and give the tracker the final keyframe poses. Background
        work that is left (the rest of a re-optimisation) is dropped."""
        try:
            self._final = self._mapping.close(timeout_s)
        finally:
            self._apply_updates()
            with self._cond:
                self.stats.mapping_lag = len(self.frontend.keyframe_poses) - self._progress.integrated
            torch.set_num_threads(self._caller_threads)
