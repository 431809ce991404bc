"""Loop detection over keyframes: bag-of-words query (paper, "Loop Closure") plus a geometric check.

For a new keyframe (paper): "The first K keyframes from BoW that are not adjacent to the current
keyframe are queried, and the two frames T_r1 and T_r2 with the highest visual similarity score and the
greatest timestamp distance are identified as the closed-loop keyframes. The threshold is defined as
the minimum similarity score between the current keyframe and its neighboring keyframes." Read here as:

1. threshold = the lowest L1 score between the query and its ``neighbours`` nearest keyframes on each
   side (in insertion order; while live only the previous ones exist); no neighbour, no query;
2. the database's ``top_k`` best keyframes outside the query's ``temporal_window`` (adjacent keyframes
   are never loop candidates); those scoring at least the threshold are accepted;
3. each accepted candidate is checked geometrically (below); failures are dropped, so that a place
   that merely looks alike is rejected instead of being applied as a loop;
4. of the verified candidates, ``r1`` is the one with the highest score and ``r2`` the one farthest in
   time from the query among the rest (``n_loop_keyframes`` = 2, the paper's two).

Geometric check: ORB matches between the query and the candidate (nearest neighbours in Hamming
distance with a ratio test, at most one query keypoint per candidate keypoint), the candidate's matched
keypoints back-projected with its depth, and ``cv2.solvePnPRansac`` against the query's pixels. The
PnP pose is then refined on its inliers with the query's own depth as well (:func:`refine_pose`), and
a match is an inlier when, under the refined pose, it reprojects within ``reprojection_error_px`` and
its two 3D points agree within ``max_point_error_m`` (scaled by the depth beyond 1 m). The pose is
accepted with at least ``min_inliers`` inliers forming at least ``min_inlier_ratio`` of the matches
that have depth in both frames. Its result is ``T_cand_query`` (query camera -> candidate camera), the
relative pose that the pose correction starts from.

Frames must be pinhole images (rectified, as the engine feeds them); depth is in metres, 0 = invalid.
A keypoint's depth is read at its nearest pixel and dropped where the 3x3 neighbourhood spans more
than :data:`DEPTH_EDGE_RATIO` of it: ORB corners often sit on occlusion edges, where the nearest depth
may belong to the background.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..config import LoopConfig
from ..geometry.se3 import invert, make_pose
from ..types import Intrinsics
from .database import KeyframeDatabase
from .features import OrbExtractor, OrbFeatures, OrbParams
from .vocabulary import BowVector, Vocabulary, l1_score

#: a keypoint's depth is unreliable where its 3x3 neighbourhood's depth range exceeds this share of it
DEPTH_EDGE_RATIO = 0.05


@dataclass(frozen=True)
class FrameFeatures:
    """What the geometric check needs of one frame: ORB keypoints and descriptors (``N``), the
    ``(N,)`` float32 depth at each keypoint (0 where missing or on a depth edge) and the pinhole camera.
    :class:`KeyframeFeatures` carries the same three fields."""

    features: OrbFeatures
    keypoint_depth_m: np.ndarray
    intrinsics: Intrinsics


def orb_params(cfg: LoopConfig) -> OrbParams:
    """The ORB settings of ``cfg``."""
    return OrbParams(cfg.n_features, cfg.orb_scale_factor, cfg.orb_levels, cfg.fast_threshold, cfg.min_image_width_px)


def frame_features(
    extractor: OrbExtractor, rgb: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics
) -> FrameFeatures:
    """ORB features of one image with their keypoints' depths."""
    feats = extractor(rgb)
    return FrameFeatures(feats, keypoint_depths(depth_m, feats.keypoints_px), intrinsics)


@dataclass(frozen=True)
class KeyframeFeatures:
    """One keyframe described for the detector: as a query all its keypoints, as a stored candidate those
    with depth (:meth:`as_candidate`).

    Attributes:
        keyframe_id: the caller's id.
        stamp_ns: capture time.
        features: ORB keypoints and descriptors (``N``).
        keypoint_depth_m: ``(N,)`` float32 depth at each keypoint, 0 where missing or on a depth edge.
        intrinsics: the (pinhole) camera.
        bow: the keyframe's bag-of-words vector.
    """

    keyframe_id: int
    stamp_ns: int
    features: OrbFeatures
    keypoint_depth_m: np.ndarray
    intrinsics: Intrinsics
    bow: BowVector

    def as_candidate(self) -> KeyframeFeatures:
        """The part a candidate's geometric check reads: the keypoints with depth (the check
        back-projects the candidate's matches, so a keypoint without depth never takes part), and the
        same bag-of-words vector (made from all of them)."""
        keep = np.flatnonzero(self.keypoint_depth_m > 0)
        if len(keep) == len(self.keypoint_depth_m):
            return self
        f = self.features
        kept = OrbFeatures(f.keypoints_px[keep], f.descriptors[keep], f.octaves[keep], f.image_size)
        return KeyframeFeatures(
            self.keyframe_id, self.stamp_ns, kept, self.keypoint_depth_m[keep], self.intrinsics, self.bow
        )


@dataclass(frozen=True)
class GeometricCheck:
    """Outcome of the geometric check of one candidate.

    Attributes:
        accepted: enough inliers (``n_inliers >= min_inliers`` and ``>= min_inlier_ratio`` times the
            matches with depth in both frames).
        T_cand_query: ``(4, 4)`` float64 pose of the query camera in the candidate camera's frame (PnP),
            None when no pose was found.
        n_matches: ratio-test matches whose candidate keypoint has depth.
        n_inliers: matches consistent with the pose in the query's pixels and depth (both needed).
        reason: why it was rejected ('' when accepted).
        T_pnp_cand_query: the PnP RANSAC pose (pixels and the candidate's depth only, before the
            refinement with the query's depth), None when PnP found none.
        n_pnp_inliers: matches within ``reprojection_error_px`` of that pose (PnP RANSAC's inliers).
    """

    accepted: bool
    T_cand_query: np.ndarray | None
    n_matches: int
    n_inliers: int
    reason: str = ""
    T_pnp_cand_query: np.ndarray | None = None
    n_pnp_inliers: int = 0


@dataclass(frozen=True)
class LoopCandidate:
    """One loop keyframe: a candidate that scored at least the threshold and passed the geometric check.

    Attributes:
        keyframe_id, stamp_ns: the candidate keyframe.
        score: its L1 score against the query.
        T_cand_query: ``(4, 4)`` float64 query camera in the candidate camera's frame.
        n_matches, n_inliers: of the geometric check.
    """

    keyframe_id: int
    stamp_ns: int
    score: float
    T_cand_query: np.ndarray
    n_matches: int
    n_inliers: int


@dataclass(frozen=True)
class LoopDetection:
    """An accepted loop of a query keyframe.

    Attributes:
        query_id: the query keyframe.
        loop_keyframes: ``r1`` (highest score) then, when there is one, ``r2`` (largest time gap to the
            query among the other verified candidates).
        threshold: the acceptance threshold (lowest similarity to the temporal neighbours).
    """

    query_id: int
    loop_keyframes: tuple[LoopCandidate, ...]
    threshold: float


@dataclass(frozen=True)
class LoopQuery:
    """Everything one query found (for logs and benchmarks); ``detection`` is what the engine uses.

    Attributes:
        query_id: the query keyframe.
        threshold: lowest similarity to the temporal neighbours (nan when there was none: no query).
        candidate_ids, candidate_scores: ``(n,)`` the top-K non-adjacent keyframes, best first.
        checks: the geometric check of each candidate at or above the threshold, in that order.
        detection: the accepted loop, or None.
    """

    query_id: int
    threshold: float
    candidate_ids: np.ndarray
    candidate_scores: np.ndarray
    checks: tuple[tuple[int, GeometricCheck], ...]
    detection: LoopDetection | None


def keypoint_depths(depth_m: np.ndarray, keypoints_px: np.ndarray) -> np.ndarray:
    """Depth ``(N,)`` float32 at ``(N, 2)`` keypoints (nearest pixel), 0 where invalid or on a depth edge
    (3x3 range above :data:`DEPTH_EDGE_RATIO` of the depth; an invalid neighbour counts as an edge)."""
    depth = np.asarray(depth_m, dtype=np.float32)
    h, w = depth.shape
    if len(keypoints_px) == 0:
        return np.zeros(0, np.float32)
    u = np.clip(np.rint(keypoints_px[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.rint(keypoints_px[:, 1]).astype(np.int64), 0, h - 1)
    kernel = np.ones((3, 3), np.uint8)
    lo = cv2.erode(depth, kernel, borderType=cv2.BORDER_REPLICATE)[v, u]
    hi = cv2.dilate(depth, kernel, borderType=cv2.BORDER_REPLICATE)[v, u]
    z = depth[v, u]
    ok = (lo > 0) & (hi - lo <= DEPTH_EDGE_RATIO * z)
    return np.where(ok, z, 0.0).astype(np.float32)


def backproject(keypoints_px: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """``(N, 2)`` pixels with ``(N,)`` depths -> ``(N, 3)`` float64 points in the camera frame (metres)."""
    k = intrinsics
    z = np.asarray(depth_m, dtype=np.float64)
    x = (keypoints_px[:, 0] - k.cx) / k.fx * z
    y = (keypoints_px[:, 1] - k.cy) / k.fy * z
    return np.stack([x, y, z], axis=1)


def match_descriptors(
    query: np.ndarray, train: np.ndarray, ratio: float, max_distance: int
) -> tuple[np.ndarray, np.ndarray]:
    """ORB matches from ``(Nq, 32)`` query to ``(Nt, 32)`` train descriptors.

    Each query descriptor's nearest train descriptor is kept when its Hamming distance is at most
    ``max_distance`` and below ``ratio`` times the second nearest's; a train descriptor claimed by
    several query descriptors keeps only the closest (ties: the lowest query index).

    Returns:
        ``(M,)`` query indices and ``(M,)`` train indices (int64), sorted by query index.
    """
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(query) == 0 or len(train) < 2:
        return none
    dist, idx = cv2.batchDistance(
        np.ascontiguousarray(query), np.ascontiguousarray(train), cv2.CV_32S, normType=cv2.NORM_HAMMING, K=2
    )
    d1, d2 = dist[:, 0].astype(np.float64), dist[:, 1].astype(np.float64)
    keep = np.flatnonzero((d1 <= max_distance) & (d1 < ratio * d2))
    if keep.size == 0:
        return none
    t = idx[keep, 0].astype(np.int64)
    order = np.lexsort((keep, d1[keep]))  # closest first, then lowest query index
    _, first = np.unique(t[order], return_index=True)
    chosen = np.sort(order[first])
    return keep[chosen].astype(np.int64), t[chosen]


def pose_residuals(
    T_query_cand: np.ndarray,
    points_cand: np.ndarray,
    pixels_query: np.ndarray,
    points_query: np.ndarray,
    intrinsics: Intrinsics,
) -> tuple[np.ndarray, np.ndarray]:
    """Per match: reprojection error (px) of the candidate's point ``(N, 3)`` in the query, and its 3D
    distance (m) to the query's point ``(N, 3)`` (meaningless where the query has no depth); points
    behind the query camera get an infinite reprojection error."""
    moved = points_cand @ T_query_cand[:3, :3].T + T_query_cand[:3, 3]
    in_front = moved[:, 2] > 1e-6
    z = np.where(in_front, moved[:, 2], 1.0)
    k = intrinsics
    reproj = np.hypot(
        k.fx * moved[:, 0] / z + k.cx - pixels_query[:, 0], k.fy * moved[:, 1] / z + k.cy - pixels_query[:, 1]
    )
    return np.where(in_front, reproj, np.inf), np.linalg.norm(moved - points_query, axis=1)


def refine_pose(
    T_query_cand: np.ndarray,
    points_cand: np.ndarray,
    pixels_query: np.ndarray,
    points_query: np.ndarray,
    tolerance_m: np.ndarray,
    intrinsics: Intrinsics,
    pixel_scale: float,
) -> np.ndarray:
    """``T_query_cand`` refined by robust least squares (soft-L1) over ``N`` matches: reprojection
    residuals in units of ``pixel_scale`` px, and, where the query has depth (``points_query[:, 2] > 0``),
    3D residuals in units of ``tolerance_m`` ``(N,)``. Returns the refined ``(4, 4)`` pose."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    has_depth = points_query[:, 2] > 0
    k = intrinsics
    R0, t0 = T_query_cand[:3, :3], T_query_cand[:3, 3]

    def residuals(x: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
        moved = points_cand @ R.T + (t0 + x[3:])
        z = np.maximum(moved[:, 2], 1e-6)
        pix = np.stack([k.fx * moved[:, 0] / z + k.cx, k.fy * moved[:, 1] / z + k.cy], axis=1)
        r_pix = ((pix - pixels_query) / pixel_scale).ravel()
        r_3d = ((moved - points_query)[has_depth] / tolerance_m[has_depth, None]).ravel()
        return np.concatenate([r_pix, r_3d])

    fit = least_squares(residuals, np.zeros(6), loss="soft_l1", f_scale=1.0, max_nfev=50, x_scale=1.0)
    R = Rotation.from_rotvec(fit.x[:3]).as_matrix() @ R0
    return make_pose(R, t0 + fit.x[3:])


class LoopDetector:
    """Keyframe database with the paper's loop query and a geometric check (see the module docstring).

    Usage, per new keyframe::

        kf = detector.add_keyframe(keyframe_id, stamp_ns, rgb, depth_m, intrinsics)
        query = detector.query(keyframe_id)
        if query.detection is not None: ...   # correct the pose with query.detection.loop_keyframes
    """

    def __init__(self, cfg: LoopConfig, vocabulary: Vocabulary | None = None):
        self.cfg = cfg
        self.vocabulary = vocabulary if vocabulary is not None else Vocabulary.load(cfg.vocabulary)
        self.extractor = OrbExtractor(orb_params(cfg))
        self.database = KeyframeDatabase(self.vocabulary.n_words)
        # insertion order = temporal order. The newest is kept whole for its own query, which comes right
        # after it is added (its keypoints without depth still count there: PnP takes the query's pixels);
        # the others as candidates (:meth:`KeyframeFeatures.as_candidate`)
        self._keyframes: list[KeyframeFeatures] = []
        self._position: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self._keyframes)

    def keyframe(self, keyframe_id: int) -> KeyframeFeatures:
        """Keyframe ``keyframe_id`` as kept: whole if it is the newest, else the part a candidate's check
        reads (``as_candidate``)."""
        return self._keyframes[self._position[int(keyframe_id)]]

    def describe(
        self, keyframe_id: int, stamp_ns: int, rgb: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics
    ) -> KeyframeFeatures:
        """ORB features, keypoint depths and BoW vector of one frame (nothing is stored)."""
        f = frame_features(self.extractor, rgb, depth_m, intrinsics)
        return KeyframeFeatures(
            int(keyframe_id),
            int(stamp_ns),
            f.features,
            f.keypoint_depth_m,
            intrinsics,
            self.vocabulary.transform(f.features.descriptors),
        )

    def add(self, keyframe: KeyframeFeatures) -> None:
        """Append a described keyframe (keyframes are added in temporal order)."""
        if keyframe.keyframe_id in self._position:
            raise ValueError(f"LoopDetector.add: keyframe {keyframe.keyframe_id} was already added")
        if self._keyframes:  # the newest so far has had its query
            self._keyframes[-1] = self._keyframes[-1].as_candidate()
        self._position[keyframe.keyframe_id] = len(self._keyframes)
        self._keyframes.append(keyframe)
        self.database.add(keyframe.keyframe_id, keyframe.bow)

    def add_keyframe(
        self, keyframe_id: int, stamp_ns: int, rgb: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics
    ) -> KeyframeFeatures:
        """:meth:`describe` then :meth:`add`; returns the stored keyframe."""
        kf = self.describe(keyframe_id, stamp_ns, rgb, depth_m, intrinsics)
        self.add(kf)
        return kf

    def threshold(self, keyframe_id: int) -> float:
        """Lowest L1 score of the keyframe to its ``neighbours`` nearest keyframes on each side (nan if none)."""
        p = self._position[int(keyframe_id)]
        n = self.cfg.neighbours
        q = self._keyframes[p].bow
        scores = [
            l1_score(q, self._keyframes[i].bow)
            for i in range(max(0, p - n), min(len(self._keyframes), p + n + 1))
            if i != p
        ]
        return float(min(scores)) if scores else float("nan")

    def query(self, keyframe_id: int) -> LoopQuery:
        """Run the paper's loop query for a keyframe already added (see the module docstring). The newest
        keyframe queries with all its keypoints, an older one with those it keeps as a candidate."""
        cfg = self.cfg
        p = self._position[int(keyframe_id)]
        q = self._keyframes[p]
        threshold = self.threshold(keyframe_id)
        no_ids = np.zeros(0, np.int64)
        if not np.isfinite(threshold):
            return LoopQuery(q.keyframe_id, threshold, no_ids, np.zeros(0), (), None)
        lo, hi = max(0, p - cfg.temporal_window), min(len(self._keyframes), p + cfg.temporal_window + 1)
        adjacent = [self._keyframes[i].keyframe_id for i in range(lo, hi)]
        result = self.database.query(q.bow, max_results=cfg.top_k, exclude_ids=adjacent)
        checks: list[tuple[int, GeometricCheck]] = []
        verified: list[LoopCandidate] = []
        for cand_id, score in zip(result.keyframe_ids.tolist(), result.scores.tolist()):
            if score < threshold:
                break  # best first: the rest are below too
            cand = self.keyframe(cand_id)
            check = self.verify(q, cand)
            checks.append((cand_id, check))
            if check.accepted:
                verified.append(
                    LoopCandidate(cand_id, cand.stamp_ns, score, check.T_cand_query, check.n_matches, check.n_inliers)
                )
        detection = None
        if verified:
            chosen = [verified[0]]  # r1: highest score (the list is best first)
            rest = verified[1:]
            if cfg.n_loop_keyframes >= 2 and rest:
                # r2: the largest time gap to the query (ties: the higher score, i.e. earlier in the list)
                gaps = [abs(c.stamp_ns - q.stamp_ns) for c in rest]
                chosen.append(rest[int(np.argmax(gaps))])
            detection = LoopDetection(q.keyframe_id, tuple(chosen), threshold)
        return LoopQuery(q.keyframe_id, threshold, result.keyframe_ids, result.scores, tuple(checks), detection)

    def place(
        self, stamp_ns: int, rgb: np.ndarray, depth_m: np.ndarray, intrinsics: Intrinsics, max_results: int
    ) -> list[LoopCandidate]:
        """Relocalisation query of a frame that is not a keyframe (nothing is stored): the database's
        ``top_k`` best keyframes, each checked by :meth:`verify`, best score first; at most
        ``max_results`` verified candidates. Unlike :meth:`query` there is no threshold and no temporal
        window: a lost camera may be anywhere, including where the last keyframes were."""
        q = self.describe(-1, stamp_ns, rgb, depth_m, intrinsics)
        result = self.database.query(q.bow, max_results=self.cfg.top_k)
        verified: list[LoopCandidate] = []
        for cand_id, score in zip(result.keyframe_ids.tolist(), result.scores.tolist()):
            cand = self.keyframe(cand_id)
            check = self.verify(q, cand)
            if check.accepted:
                verified.append(
                    LoopCandidate(cand_id, cand.stamp_ns, score, check.T_cand_query, check.n_matches, check.n_inliers)
                )
                if len(verified) >= max_results:
                    break
        return verified

    def verify(self, query: KeyframeFeatures, cand: KeyframeFeatures) -> GeometricCheck:
        """Geometric check of ``cand`` for ``query`` (:func:`geometric_check`)."""
        return geometric_check(query, cand, self.cfg)


def enough_inliers(n_inliers: int, n_pairs: int, cfg: LoopConfig) -> bool:
    """The geometric check's acceptance rule: at least ``min_inliers`` inliers, and at least
    ``min_inlier_ratio`` of the ``n_pairs`` matches they were counted among."""
    return n_inliers >= cfg.min_inliers and n_inliers >= cfg.min_inlier_ratio * n_pairs


def geometric_check(
    query: FrameFeatures | KeyframeFeatures, cand: FrameFeatures | KeyframeFeatures, cfg: LoopConfig
) -> GeometricCheck:
    """Geometric check of ``cand`` for ``query`` (the module docstring): matches, the candidate's depth
    back-projection, PnP RANSAC, refinement with the query's depth; ``T_cand_query`` when accepted."""
    with_depth = np.flatnonzero(cand.keypoint_depth_m > 0)
    if len(with_depth) < max(4, cfg.min_inliers):
        return GeometricCheck(False, None, 0, 0, f"{len(with_depth)} candidate keypoints with depth")
    qi, ti = match_descriptors(
        query.features.descriptors, cand.features.descriptors[with_depth], cfg.match_ratio, cfg.max_match_distance
    )
    n_matches = len(qi)
    if n_matches < max(4, cfg.min_inliers):
        return GeometricCheck(False, None, n_matches, 0, f"{n_matches} matches")
    ci = with_depth[ti]
    points_cand = backproject(cand.features.keypoints_px[ci], cand.keypoint_depth_m[ci], cand.intrinsics)
    pixels_query = query.features.keypoints_px[qi].astype(np.float64)
    ok, rvec, tvec, pnp_inliers = cv2.solvePnPRansac(
        points_cand,
        pixels_query,
        query.intrinsics.K,
        None,
        iterationsCount=cfg.ransac_iterations,
        reprojectionError=cfg.reprojection_error_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or pnp_inliers is None or len(pnp_inliers) < 3:
        return GeometricCheck(False, None, n_matches, 0, "PnP RANSAC found no pose")
    T_query_cand = make_pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3))  # x_query = R x_cand + t
    pnp = {"T_pnp_cand_query": invert(T_query_cand), "n_pnp_inliers": len(pnp_inliers)}

    # Depth check and refinement. From pixels alone, points at similar depths leave a sideways
    # translation and a rotation that cancel each other (40 cm and 5 degrees at 4.5 m on the
    # synthetic 160x120 loop, with every inlier a true match); the query's own depth settles it.
    # The PnP pose is refined on its inliers by both residuals at once (pixels in the query, and
    # 3D distance to the query's back-projected point in units of the depth tolerance), robustly:
    # real depth is not consistent enough between frames for a pure 3D fit (Kinect: 2-3 cm at
    # 1.5 m), simulated pixels at 160x120 not precise enough for a pure PnP.
    depth_q = query.keypoint_depth_m[qi].astype(np.float64)
    points_query = backproject(pixels_query, depth_q, query.intrinsics)
    tolerance_m = cfg.max_point_error_m * np.maximum(1.0, depth_q)
    start = pnp_inliers.reshape(-1)
    T_query_cand = refine_pose(
        T_query_cand,
        points_cand[start],
        pixels_query[start],
        points_query[start],
        tolerance_m[start],
        query.intrinsics,
        cfg.reprojection_error_px,
    )
    reproj, dist3 = pose_residuals(T_query_cand, points_cand, pixels_query, points_query, query.intrinsics)
    # an inlier reprojects within the threshold and agrees with the query's depth: without that, a
    # keypoint without depth in the query would count on its pixel alone
    consistent = (reproj <= cfg.reprojection_error_px) & (depth_q > 0) & (dist3 <= tolerance_m)
    n_inliers = int(consistent.sum())
    n_checkable = int(np.count_nonzero(depth_q > 0))  # matches with depth on both sides
    T_cand_query = invert(T_query_cand)
    if not enough_inliers(n_inliers, n_checkable, cfg):
        return GeometricCheck(
            False,
            T_cand_query,
            n_matches,
            n_inliers,
            f"{n_inliers} inliers of {n_checkable} matches with depth in both frames",
            **pnp,
        )
    return GeometricCheck(True, T_cand_query, n_matches, n_inliers, **pnp)
