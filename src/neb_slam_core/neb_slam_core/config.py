"""Configuration: frozen dataclasses, one per subsystem, with the paper's defaults.

Components take their own sub-config (never the whole tree). YAML files with ``inherit_from`` and the
per-dataset presets build on these classes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class HashGridConfig:
    """Multi-resolution hash encoding of one neural block (paper: L=16, F=2, R_min=16, T=2^15).

    ``max_resolution`` is the finest grid resolution over the block's edge: edge / voxel size
    (5 m / 2 cm = 250).
    """

    n_levels: int = 16
    n_features_per_level: int = 2
    log2_hashmap_size: int = 15
    base_resolution: int = 16
    max_resolution: int = 250
    init_scale: float = 1e-4

    @property
    def table_size(self) -> int:
        return 1 << self.log2_hashmap_size

    @property
    def n_output_dims(self) -> int:
        return self.n_levels * self.n_features_per_level


@dataclass(frozen=True)
class OneBlobConfig:
    """One-blob encoding of world coordinates (16 bins per axis).

    An unknown scene has no bounds to normalise by, so each axis is encoded periodically with
    ``period_m``: the code of x and of x + period_m is the same, and the block's hash features tell
    them apart. The period must exceed a block's edge so that no block sees a repeated code.
    """

    n_bins: int = 16
    period_m: float = 10.0


@dataclass(frozen=True)
class DecoderConfig:
    """The two shared MLPs of the paper: geometry (one-blob + hash -> sdf + feature) and colour."""

    hidden_dim: int = 32
    feature_dim: int = 15


@dataclass(frozen=True)
class BlockConfig:
    """Neural blocks and their allocation (paper: 5 m cubes, tau threshold 0.2).

    ``blend_m``: where blocks overlap, a point's features are the mean of the blocks' features (the
    paper), weighted by a window that falls linearly to 0 over the last ``blend_m`` metres before each
    block's faces. Deep in an overlap this is the plain mean; at a face the leaving block's weight is 0,
    so features (and rendered depth) are continuous across seams. 0 gives the paper's plain mean.

    ``observed_voxel_m`` (ours; 0: no record): each block records which of its voxels of this edge some
    keyframe has seen (:meth:`~neb_slam_core.scene.block_map.BlockMap.mark_observed`), so that tracking
    can leave out space the map has never been fitted to (``tracking.observed_only``).

    ``alloc_centre``: where a new block goes. ``mean``: the paper's, the mean of the points outside every
    block. ``cover`` (ours): the same where its cube holds every outside point, else the cube of a mean
    shift over the outside points that holds the most (:func:`~neb_slam_core.scene.block_map.covering_centre`),
    so that outside points on two sides of the mapped space get a block each instead of blocks stacked
    between them.
    """

    edge_m: float = 5.0
    grid: HashGridConfig = HashGridConfig()
    alloc_threshold: float = 0.2
    alloc_n_points: int = 2000
    alloc_centre: str = "cover"
    blend_m: float = 0.5
    observed_voxel_m: float = 0.05


@dataclass(frozen=True)
class SamplingConfig:
    """Samples per ray: ``n_uniform`` between near and far plus ``n_surface`` within +/- ``surface_range_m``
    of the measured depth (paper: 32 + 11; ScanNet 96 + 21).

    ``skip_behind_m`` (ours; 0 = off, the paper evaluates every sample): on a ray with measured depth,
    samples more than this behind it are not evaluated and count as outside every block. They carry no
    loss (the SDF band ends at the truncation distance behind the measurement) and no rendering weight
    once the map's surface lies within ``skip_behind_m - truncation`` of the measurement (rendering
    drops what lies more than the truncation behind the first surface), so the result is unchanged
    there; it must be at least the truncation distance. On TUM (depth about 1.3 m, far 5 m) they are
    most of the uniform samples.
    """

    n_uniform: int = 32
    n_surface: int = 11
    near_m: float = 0.1
    far_m: float = 6.0
    surface_range_m: float = 0.05
    skip_behind_m: float = 0.3


@dataclass(frozen=True)
class LossWeights:
    """Weights of the five losses (paper: colour 5, depth 0.1, sdf 1000, free space 10, smoothness 1e-6)."""

    colour: float = 5.0
    depth: float = 0.1
    sdf: float = 1000.0
    free_space: float = 10.0
    smoothness: float = 1e-6


@dataclass(frozen=True)
class RenderConfig:
    """Volume rendering and its losses: truncation ``truncation_m`` (10 cm; TUM 5 cm).

    ``depth_noise_weights`` (ours; False: the paper, every ray's depth counts alike): the depth, SDF and
    free-space losses of each ray weighed by the inverse variance of its depth measurement, normalised to
    a mean of 1 over the rays with depth (:func:`~neb_slam_core.render.losses.depth_noise_weights`). A
    structured-light or stereo camera measures depth with an error that grows with the square of the
    depth, so a point 3 m away is an order of magnitude less certain than one at 1 m; it applies to both
    tracking and mapping, which minimise the same objective.
    """

    truncation_m: float = 0.10
    sampling: SamplingConfig = SamplingConfig()
    weights: LossWeights = LossWeights()
    smoothness_points: int = 512
    smoothness_step_m: float = 0.02
    depth_noise_weights: bool = False


@dataclass(frozen=True)
class MeshConfig:
    """Mesh extraction: marching cubes at ``voxel_size_m``; surfaces farther than ``cull_distance_m`` from
    every observed point are removed."""

    voxel_size_m: float = 0.02
    cull_distance_m: float = 0.10
    batch_points: int = 65536


def config_to_dict(cfg) -> dict:
    """A config dataclass (nested) -> plain dict, fields in declaration order (YAML/JSON friendly).

    Leaves that are subclasses of the builtin types (``numpy.float64`` is a ``float``) become the builtin
    itself, so that safe YAML and JSON writers accept them.
    """
    import dataclasses

    out = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out[f.name] = config_to_dict(value)
        else:
            out[f.name] = _builtin_value(value)
    return out


def _builtin_value(value):
    for kind in (bool, int, float, str):  # bool first: it is a subclass of int
        if isinstance(value, kind):
            return kind(value)
    return value


def key_source(sources: dict[str, str] | None, key: str) -> str | None:
    """Where dotted ``key`` was set according to ``sources`` (dotted key -> file or override): the entry of
    ``key`` itself, else of its nearest listed parent (``"a.b"`` for ``"a.b.c"``), else of ``""``; None
    when ``sources`` is empty."""
    if not sources:
        return None
    k = key
    while True:
        if k in sources:
            return sources[k]
        if not k:
            return None
        k = k.rpartition(".")[0]


def _config_error(sources: dict[str, str] | None, key: str, problem: str):
    from .errors import ConfigError

    where = key_source(sources, key)
    return ConfigError(f"{where + ': ' if where else ''}{key}: {problem}")


def config_from_dict(cls, data: dict, where: str = "", sources: dict[str, str] | None = None):
    """Build config dataclass ``cls`` from a (nested) dict.

    Unknown keys and values of the wrong type raise :class:`ConfigError` naming the dotted key (and, when
    ``sources`` maps dotted keys to the file or override that set them, that file; see :func:`key_source`).
    Nested dataclass fields are built recursively (an empty or null section counts as ``{}``), missing
    keys take the defaults, integers are accepted for float fields (and converted); nothing else is
    converted: ``"0.1"`` for a float, ``1.0`` for an integer or ``1`` for a boolean are errors.
    Range checks are :func:`neb_slam_core.config_io.validate`'s job.
    """
    import dataclasses
    import difflib
    import typing

    prefix = where + "." if where else ""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise _config_error(
            sources,
            where or cls.__name__,
            f"expected a mapping of {cls.__name__} parameters, got {type(data).__name__} {data!r}",
        )
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if key not in fields:
            close = difflib.get_close_matches(str(key), list(fields), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise _config_error(
                sources, name, f"unknown parameter of {cls.__name__}{hint} (known: {', '.join(fields)})"
            )
        kind = hints[key]
        if dataclasses.is_dataclass(kind):
            kwargs[key] = config_from_dict(kind, value, name, sources)
        elif kind is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise _config_error(sources, name, f"expected a number, got {value!r}")
            kwargs[key] = float(value)
        elif kind is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise _config_error(sources, name, f"expected an integer, got {value!r}")
            kwargs[key] = int(value)
        elif kind is bool:
            if not isinstance(value, bool):
                raise _config_error(sources, name, f"expected true or false, got {value!r}")
            kwargs[key] = value
        elif kind is str:
            if not isinstance(value, str):
                raise _config_error(sources, name, f"expected a string, got {value!r}")
            kwargs[key] = value
        else:
            kwargs[key] = value
    return cls(**kwargs)


@dataclass(frozen=True)
class TrackingConfig:
    """Pose optimisation by rendering (paper: N_t = 1024 rays, 10 iterations, lr 1e-3; TUM 1e-2).

    ``failure_ratio``: a frame whose final depth residual (the median over its rays) exceeds this
    multiple of the running median and ``failure_min_residual_m``, or that has fewer than
    ``min_valid_rays`` rays inside blocks, is reported as a tracking failure and keeps the
    constant-velocity prediction. The absolute floor keeps noise-free data (sub-millimetre residuals)
    from calling a 1-2 cm inaccuracy a failure: a failed frame adds nothing to the map, so false alarms
    starve it.

    ``method``: ``gauss_newton`` (ours: Levenberg-Marquardt on the paper's objective, at most
    ``iterations`` steps, no learning rate; it starts with damping ``gn_damping`` times the Gauss-Newton
    matrix' diagonal and stops once the step it proposes would move the camera, and points 1 m in front
    of it, by less than ``gn_stop_step_m``; that step is not taken) or ``adam`` (the paper:
    ``iterations`` Adam steps at ``lr``). Gauss-Newton reaches in a few steps the pose that Adam
    approaches in tens (``benchmarks/tracking.py``).

    ``motion_model``: the constant-velocity prediction (:meth:`neb_slam_core.slam.Frontend.predict`):
    ``frames`` (the paper's: by frame count) or ``stamps`` (by the stamps of the last two tracked frames,
    so that dropped or failed frames between them do not matter; at most ``max_extrapolation`` times
    their motion).

    ``prediction`` (ours; ``motion``: the paper's constant velocity, by ``motion_model``): ``features``
    starts tracking from the last tracked frame's pose moved by the relative pose from ORB matches
    between the two frames (the loop detector's geometric check with the ``loop`` ORB and matching
    settings, :class:`neb_slam_core.loop.motion.FeatureMotion`; its PnP pose where only the current
    frame's depth disagrees), and from the motion model's prediction where neither verifies. It costs
    an ORB extraction and a PnP per frame and keeps the prediction within the tracker's basin when
    frames are far apart (a live engine that drops frames, abrupt turns and stops).

    ``gn_stop_step_m`` 0.5 mm: the objective's minimum itself moves by millimetres between two draws of
    the ``n_rays`` pixels, so converging much further than that buys nothing but steps.

    ``coarse_rays`` (``gauss_newton`` only; 0: off, the paper's single stage): a first stage on that many
    of the ``n_rays`` pixels, until a step moves less than ``coarse_stop_step_m``, then the stage on all
    of them from its pose. Each stage takes at most ``iterations`` steps. A prediction far from the
    minimum (frames dropped, fast motion) then costs cheap steps instead of full ones.

    ``relocalise``: after a tracking failure the frontend is lost (it allocates nothing, makes no
    keyframe, predicts the last tracked pose) until a frame passes the failure test again. Each lost
    frame is re-tracked from the last tracked pose and, where the engine has a keyframe database (the
    loop closer's, ``loop.enabled``), from the poses of the keyframes it is verified against; the start
    whose tracked pose has the lowest depth residual is judged. False (the default, as the paper): only
    the prediction is tracked. In the live engine each extra attempt delays the next frame, and a pose
    that passes the failure test can still be a wrong one, so it is off in every preset.

    ``observed_only`` (ours; False: the paper): samples in space no keyframe has seen
    (``block.observed_voxel_m``) count as outside every block, so a ray whose measured surface lies there
    is left out. The map there is whatever its initialisation and its neighbours' fitting made of it:
    its free space and surfaces are not the scene's, and they pull a camera that moved towards new
    space back towards the space the map knows.

    ``colour_timing`` (ours; False: the paper, the colour image as taken): a frame whose colour image was
    taken at another time than its depth image (the loader's ``colour_stamp_ns`` / ``depth_stamp_ns``
    extras) has its colour resampled to the depth image's time, moved by the motion between the last two
    tracked frames (:mod:`~neb_slam_core.geometry.colour_timing`), before it is tracked and kept.

    ``colour_scale`` (ours; 1: the paper, tracking and mapping weigh the colour loss alike): tracking
    weighs the colour loss by this times ``render.weights.colour``; mapping keeps the weight as it is. On
    a hand-held camera the colour image is the part of a frame that motion blur and a colour camera
    registered to depth only approximately spoil, and a pose fitted to it moves with both; the geometry
    terms (depth, SDF, free space) constrain a pose in a scene with depth relief on their own (0: geometry
    alone).

    ``motion_prior_m_s2``, ``motion_prior_rad_s2`` (ours; 0: the paper, where the motion model's
    prediction only starts the optimisation): the tracked pose is fused with the constant-velocity
    prediction, each weighed by the inverse of its covariance (a Kalman update,
    :func:`~neb_slam_core.tracking.tracker.fuse`): the tracked pose's is the one tracking reports, the
    prediction's the error these accelerations of the camera (linear, angular) cause over the frame
    interval (:func:`~neb_slam_core.tracking.tracker.motion_prior`). A pose that the pixels drawn leave
    uncertain by millimetres then moves towards where the camera's motion puts it. There is a prior
    where the motion model extrapolates a velocity (two tracked frames before the frame, not after a
    failure), whichever pose tracking starts from (a ``features`` prediction too); relocalisation's
    starts carry none. 0 in one leaves that part to the frame alone.
    """

    n_rays: int = 1024
    iterations: int = 10
    lr: float = 1e-3
    border_px: int = 0
    failure_ratio: float = 8.0
    failure_min_residual_m: float = 0.03
    min_valid_rays: int = 64
    method: str = "gauss_newton"
    gn_damping: float = 1e-4
    gn_stop_step_m: float = 5e-4
    motion_model: str = "frames"
    max_extrapolation: float = 4.0
    prediction: str = "motion"
    coarse_rays: int = 0
    coarse_stop_step_m: float = 2e-3
    relocalise: bool = False
    observed_only: bool = True
    colour_timing: bool = False
    colour_scale: float = 1.0
    motion_prior_m_s2: float = 0.0
    motion_prior_rad_s2: float = 0.0


@dataclass(frozen=True)
class KeyframeConfig:
    """Keyframes: every ``every``-th frame plus allocating frames; each keeps ``pixel_fraction`` of its pixels.

    ``every_s`` (0: off, the paper's count only): a tracked frame stamped at least this long after the
    last keyframe is a keyframe too, and the map is optimised after it. A live engine that tracks only
    some of the camera's frames counts them too slowly (every 5th tracked frame is seconds of video apart),
    so its map would lag behind the camera; stamps do not depend on how many frames were processed.
    """

    every: int = 5
    pixel_fraction: float = 0.05
    every_s: float = 0.0


@dataclass(frozen=True)
class MappingConfig:
    """Joint optimisation of blocks, decoders and keyframe poses (paper: first frame 200 iterations;
    every 5 frames 10 iterations (TUM 20) of N_m = 2048 rays plus N_a = 512 from the newest block's
    keyframes; learning rates 1e-2 grids and decoders, 1e-3 keyframe poses, the first keyframe fixed)."""

    every: int = 5
    iterations: int = 10
    first_iterations: int = 200
    n_rays: int = 2048
    n_rays_newest_block: int = 512
    grid_lr: float = 1e-2
    decoder_lr: float = 1e-2
    pose_lr: float = 1e-3
    optimise_poses: bool = True


@dataclass(frozen=True)
class LoopConfig:
    """Loop closure: bag-of-words place recognition over keyframes (paper, "Loop Closure").

    A new keyframe's ORB features (``n_features`` per image, pyramid ``orb_scale_factor`` x
    ``orb_levels``, FAST threshold ``fast_threshold``; images narrower than ``min_image_width_px`` are
    upsampled first) become a TF-IDF vector of the vocabulary ``vocabulary`` ("" = the one shipped in
    ``neb_slam_core/loop/data``). The database returns the ``top_k`` best keyframes outside the
    ``temporal_window`` keyframes before and after the query (the paper's "not adjacent"); those
    scoring at least the lowest similarity of the query to its ``neighbours`` nearest keyframes on each
    side (the paper's threshold) and passing the geometric check are accepted, and of them the
    ``n_loop_keyframes`` (paper: 2) are taken: the highest score, then the largest time gap.

    Geometric check: ORB matches (Hamming distance at most ``max_match_distance`` bits, nearest below
    ``match_ratio`` times the second nearest), the candidate's matched keypoints back-projected with its
    depth, the relative pose by PnP RANSAC (``ransac_iterations``, inlier reprojection error
    ``reprojection_error_px``), refined with the query's own depth as well, and its inliers counted: a
    match reprojecting within ``reprojection_error_px`` whose two 3D points agree within
    ``max_point_error_m`` (times the depth beyond 1 m). Accepted with at least ``min_inliers`` inliers
    that are at least ``min_inlier_ratio`` of the matches with depth in both frames.

    Correction (``loop/correction.py``): the current keyframe's pose minimises the paper's reprojection
    objective over ``correction_pixels`` of its pixels through the loop keyframes' depth maps (kept every
    ``depth_stride``-th pixel), starting from the geometric check's pose; it is applied when the fit
    ends below ``max_fit_rms_px`` with at least ``min_valid_share`` of the pixel/keyframe pairs valid,
    and when it moves the keyframe by at least ``min_correction_cm`` or ``min_correction_deg`` (a
    smaller one is within what mapping refines anyway; each applied loop costs a re-optimisation, and
    on TUM fr1_xyz turns of about half a degree gain the ATE little). Then the correction is spread along the loop by
    a pose graph whose edges are the tracked relative poses and, beside them, each keyframe's depth
    registered (by the same objective and tests) against the ``register_neighbours`` keyframes before
    it (0: tracked edges only),
    and the map re-optimised in two stages: ``map_iterations`` with the poses fixed, then
    ``joint_iterations`` of poses and map (the paper gives no counts; ``benchmarks/loop_ablation.py``
    measures ours).
    """

    enabled: bool = True
    vocabulary: str = ""
    n_features: int = 1000
    orb_scale_factor: float = 1.2
    orb_levels: int = 8
    fast_threshold: int = 20
    min_image_width_px: int = 320
    top_k: int = 10
    temporal_window: int = 10
    neighbours: int = 3
    n_loop_keyframes: int = 2
    match_ratio: float = 0.8
    max_match_distance: int = 64
    ransac_iterations: int = 200
    reprojection_error_px: float = 3.0
    max_point_error_m: float = 0.015
    min_inliers: int = 30
    min_inlier_ratio: float = 0.2
    correction_pixels: int = 2000
    depth_stride: int = 2
    max_fit_rms_px: float = 2.0
    min_valid_share: float = 0.3
    min_correction_cm: float = 1.0
    min_correction_deg: float = 0.75
    register_neighbours: int = 2
    map_iterations: int = 200
    joint_iterations: int = 50


@dataclass(frozen=True)
class LiveConfig:
    """The concurrent engine (:mod:`neb_slam_core.live`: ``neb-slam run --live``, the ROS ``slam`` node
    without lockstep), where tracking never waits for mapping or loop closure.

    ``first_iterations``: map-only steps on the first frame before the second frame is tracked (the
    rest of ``mapping.first_iterations`` runs in the background). ``chunk_iterations``: background work
    (that rest, a loop correction's re-optimisation) runs in chunks of this many steps between
    keyframes. ``torch_threads``: torch's intra-op threads of each thread that runs the engine (0: torch's
    default; the ``live`` preset sets 1, so that on two cores the tracker and the mapper each keep one
    busy instead of competing for both); the ROS nodes apply it too. ``max_gap_s``: the engine tracks
    the newest frame that arrived, but none more than this after the last processed frame (0: the newest,
    however far): a frame far ahead of the last pose lies outside the tracker's basin, so after a wait
    (the first map) the engine catches up in steps instead of jumping. ``max_turn_deg``: nor further
    than the camera turns by this at the rate between the last two tracked frames (0: no bound):
    feature matches and the tracker's basin span a few degrees, so in a fast turn the engine takes
    frames closer together, and catches up from the queued frames once the turn slows. ``max_gap_growth``:
    nor more than this many times the interval between the last two tracked frames after the last one
    (0: no bound): that interval measures the turn rate ``max_turn_deg`` extrapolates, a short one
    measures it poorly (a fraction of a degree against the tracker's noise), and a hand-held pan
    speeds up within a fraction of a second, so after a fast turn the engine catches up in growing
    steps, each measuring the rate anew. ``background_nice``: the mapping
    and loop threads (and the ROS ``mapper`` and ``loop_closer`` nodes' engine threads) run this much
    nicer than tracking (0: as nice as it), so that tracking keeps a core when all are busy
    (:func:`neb_slam_core.engine_process.lower_thread_priority`). ``mapping_process``: mapping and loop
    closure run in a child process (:class:`neb_slam_core.live_mapping.ProcessMapping`), so that they do not
    take turns with tracking on one Python interpreter; False keeps them in threads of the tracker's process.
    ``update_tolerance``, ``update_float16`` and ``update_delta_step``: how the mapping side's map updates
    carry the tables to the tracker (:mod:`neb_slam_core.scene.map_update`): a changed table row goes once
    one of its values is more than ``update_tolerance`` off the tracker's copy, as float16 with
    ``update_float16`` (0 and False: every change, exact); with ``update_delta_step`` (a power of two; 0:
    none) a block the tracker has goes instead as every value's change in whole steps, one byte each (two
    where a change needs them), compressed, which keeps the tracker's copy within half a step of the
    mapper's.
    """

    first_iterations: int = 30
    chunk_iterations: int = 10
    torch_threads: int = 0
    max_gap_s: float = 0.0
    max_turn_deg: float = 0.0
    max_gap_growth: float = 0.0
    background_nice: int = 0
    mapping_process: bool = True
    update_tolerance: float = 0.0
    update_float16: bool = False
    update_delta_step: float = 0.0


@dataclass(frozen=True)
class SlamConfig:
    """The whole engine's configuration; each component receives only its own part."""

    block: BlockConfig = BlockConfig()
    one_blob: OneBlobConfig = OneBlobConfig()
    decoder: DecoderConfig = DecoderConfig()
    render: RenderConfig = RenderConfig()
    tracking: TrackingConfig = TrackingConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    mapping: MappingConfig = MappingConfig()
    mesh: MeshConfig = MeshConfig()
    grid_backend: str = "auto"
    device: str = "cpu"
    seed: int = 0
    loop: LoopConfig = LoopConfig()
    live: LiveConfig = LiveConfig()


def is_delta_step(step: float) -> bool:
    """Whether ``step`` can be ``LiveConfig.update_delta_step``: 0 (none) or a power of two at most 1,
    so that a whole number of steps (int16) times the step is exact in float32."""
    if isinstance(step, bool) or not isinstance(step, (int, float)):
        return False
    return step == 0 or (0 < step <= 1 and math.frexp(step)[0] == 0.5)
