"""Place recognition (loop detection) quality and speed: vocabulary load, query time, recall, false loops.

Figures (JSON keys):

- ``vocab_load_s``: seconds to load the shipped vocabulary (the median of 5 loads; ``vocab_load_s_first``
  is the first, with a cold page cache for the file). Target < 1 s.
- ``query_ms_1000``: median milliseconds of one database query (the paper's top-K, adjacent keyframes
  excluded) with 1,000 keyframes in the database; the keyframes are the frames of the ``default``
  synthetic preset with seeds 0..3 (160x120, generated once under ``.cache/scenes/``). Target < 20 ms.
  Also ``describe_ms`` (ORB + words of one keyframe) and ``detect_ms`` (a whole query, geometric checks
  included) on the synthetic loop, medians.
- Synthetic loop (``default`` preset, seed 0, 300 frames, the route returns to its start): keyframes
  every 5th frame, each added then queried, as the engine will. A ground-truth revisit of a query is an
  earlier keyframe outside the temporal window whose view overlaps the query's by more than 50% both
  ways: it sees more than half of the query's valid depth pixels and the query more than half of its
  own (projected with the ground-truth poses and depth, inside the image and not occluded).
  ``revisit_recall`` = queries with a revisit that got an accepted loop / queries with a revisit.
  ``revisit_recall_one_sided`` counts a revisit when the keyframe sees half of the query, whatever
  share of its own view that is (this adds views of a place from 3 m away at 45 degrees, where the
  place fills a seventh of the image: not what BoW place recognition is expected to find).
- False loops: an accepted loop keyframe whose estimated relative pose ``T_cand_query`` differs from
  the ground truth's by more than 10 cm or 5 degrees (``--max-error-cm``, ``--max-error-deg``).
  ``false_loops_synthetic`` on the loop above; ``false_loops_tum`` on the 300 TUM fr1_xyz frames in
  ``../shared/data/tum_fr1_xyz_300`` (rectified as the engine does, keyframes every 5th frame). fr1_xyz
  moves little, so frames far apart in time do see the same desk: loops found there are real
  re-observations, and only a wrong relative pose counts as false (``tum_detections`` says how many
  were accepted, ``tum_pose_error_*`` how good their poses are).

Usage::

    .venv/bin/python benchmarks/place_recognition.py --json place_recognition.json
    .venv/bin/python benchmarks/place_recognition.py --skip-tum --set top_k=5
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from common import record

from neb_slam_core.config import LoopConfig
from neb_slam_core.datasets import open_dataset
from neb_slam_core.geometry.rectify import Rectifier
from neb_slam_core.geometry.se3 import invert
from neb_slam_core.loop.database import KeyframeDatabase
from neb_slam_core.loop.detector import LoopDetector
from neb_slam_core.loop.vocabulary import Vocabulary, shipped_vocabulary_path
from neb_slam_core.synth.generate import generate

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("NEB_SLAM_SHARED_DATA", REPO.parent / "shared" / "data"))
SCENES = REPO / ".cache" / "scenes"
KEYFRAME_EVERY = 5
MIN_OVERLAP = 0.5


def scene(seed: int) -> Path:
    name = "default" if seed == 0 else f"default-seed{seed}"
    return generate("default", SCENES / name, seed=seed, progress=False)


def pose_error(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """Translation (cm) and rotation (deg) of ``T_gt^-1 T_est``."""
    E = invert(T_gt) @ T_est
    angle = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(E[:3, 3]) * 100.0), float(angle)


def view_overlap(frame_a, frame_b, step: int = 4) -> float:
    """Share of ``frame_a``'s valid depth pixels (every ``step``-th) that ``frame_b`` sees: inside its
    image, in front of it and not occluded (its own depth there within 5% + 2 cm). Ground-truth poses."""
    k = frame_a.intrinsics
    v, u = np.mgrid[0 : k.height : step, 0 : k.width : step]
    z = frame_a.depth_m[v, u]
    ok = z > 0
    u, v, z = u[ok], v[ok], z[ok].astype(np.float64)
    if z.size == 0:
        return 0.0
    p_a = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z, np.ones_like(z)])
    p_b = (invert(frame_b.T_world_cam) @ frame_a.T_world_cam @ p_a)[:3]
    kb = frame_b.intrinsics
    front = p_b[2] > 1e-3
    ub = np.rint(kb.fx * p_b[0] / np.where(front, p_b[2], 1.0) + kb.cx).astype(np.int64)
    vb = np.rint(kb.fy * p_b[1] / np.where(front, p_b[2], 1.0) + kb.cy).astype(np.int64)
    inside = front & (ub >= 0) & (ub < kb.width) & (vb >= 0) & (vb < kb.height)
    zb = np.zeros_like(z)
    zb[inside] = frame_b.depth_m[vb[inside], ub[inside]]
    seen = inside & (zb > 0) & (np.abs(zb - p_b[2]) < 0.05 * p_b[2] + 0.02)
    return float(seen.mean())


@dataclasses.dataclass
class SequenceResult:
    n_keyframes: int
    n_queries_with_revisit: int
    n_revisits_found: int
    n_queries_with_one_sided_revisit: int
    n_one_sided_revisits_found: int
    n_detections: int
    n_loop_keyframes: int
    n_false: int
    n_unscored: int
    errors_cm: list
    errors_deg: list
    describe_ms: list
    detect_ms: list
    detections: list


def run_sequence(
    frames: list, cfg: LoopConfig, vocab: Vocabulary, max_cm: float, max_deg: float, with_revisits: bool
) -> SequenceResult:
    """Add the keyframes one by one, query each, and score the accepted loops against ground truth."""
    det = LoopDetector(cfg, vocab)
    res = SequenceResult(len(frames), 0, 0, 0, 0, 0, 0, 0, 0, [], [], [], [], [])
    for i, f in enumerate(frames):
        t0 = time.perf_counter()
        det.add_keyframe(i, f.stamp_ns, f.rgb, f.depth_m, f.intrinsics)
        t1 = time.perf_counter()
        query = det.query(i)
        t2 = time.perf_counter()
        res.describe_ms.append((t1 - t0) * 1e3)
        res.detect_ms.append((t2 - t1) * 1e3)
        revisit = one_sided = False
        if with_revisits and f.T_world_cam is not None:
            earlier = [j for j in range(0, max(0, i - cfg.temporal_window)) if frames[j].T_world_cam is not None]
            seen = [j for j in earlier if view_overlap(f, frames[j]) > MIN_OVERLAP]
            one_sided = bool(seen)
            revisit = any(view_overlap(frames[j], f) > MIN_OVERLAP for j in seen)
            res.n_queries_with_revisit += revisit
            res.n_queries_with_one_sided_revisit += one_sided
        d = query.detection
        if d is None:
            continue
        res.n_detections += 1
        res.n_revisits_found += revisit
        res.n_one_sided_revisits_found += one_sided
        for c in d.loop_keyframes:
            res.n_loop_keyframes += 1
            if f.T_world_cam is None or frames[c.keyframe_id].T_world_cam is None:
                res.n_unscored += 1  # no ground truth to judge it by
                continue
            gt = invert(frames[c.keyframe_id].T_world_cam) @ f.T_world_cam
            e_cm, e_deg = pose_error(c.T_cand_query, gt)
            res.errors_cm.append(e_cm)
            res.errors_deg.append(e_deg)
            false = e_cm > max_cm or e_deg > max_deg
            res.n_false += false
            res.detections.append(
                {
                    "query": i,
                    "loop_keyframe": c.keyframe_id,
                    "score": round(c.score, 4),
                    "threshold": round(d.threshold, 4),
                    "inliers": c.n_inliers,
                    "matches": c.n_matches,
                    "error_cm": round(e_cm, 2),
                    "error_deg": round(e_deg, 2),
                    "false": bool(false),
                }
            )
    return res


def keyframes_of(path: Path, rectify: bool) -> list:
    ds = open_dataset(path)
    rect = Rectifier()
    frames = [ds[i] for i in range(0, len(ds), KEYFRAME_EVERY)]
    frames = [rect(f) if rectify else f for f in frames]
    missing = sum(f.T_world_cam is None for f in frames)
    if missing:  # kept (the engine would have them too); loops involving them are not scored
        print(f"{path}: {missing} of {len(frames)} keyframes have no ground-truth pose", file=sys.stderr)
    return frames


def query_time_1000(cfg: LoopConfig, vocab: Vocabulary, n_keyframes: int = 1000, n_queries: int = 200) -> dict:
    det = LoopDetector(cfg, vocab)
    vectors = []
    for seed in range(4):
        ds = open_dataset(scene(seed))
        for i in range(len(ds)):
            if len(vectors) == n_keyframes:
                break
            f = ds[i]
            vectors.append(det.describe(len(vectors), f.stamp_ns, f.rgb, f.depth_m, f.intrinsics).bow)
    db = KeyframeDatabase(vocab.n_words)
    for i, v in enumerate(vectors):
        db.add(i, v)
    rng = np.random.default_rng(0)
    times = []
    for q in rng.choice(len(vectors), size=n_queries, replace=False).tolist():
        adjacent = list(range(max(0, q - cfg.temporal_window), min(len(vectors), q + cfg.temporal_window + 1)))
        t0 = time.perf_counter()
        db.query(vectors[q], max_results=cfg.top_k, exclude_ids=adjacent)
        times.append((time.perf_counter() - t0) * 1e3)
    words = [len(v) for v in vectors]
    return {
        "query_ms_1000": round(statistics.median(times), 3),
        "query_ms_1000_p90": round(float(np.percentile(times, 90)), 3),
        "db_keyframes": len(vectors),
        "words_per_keyframe_mean": round(float(np.mean(words)), 1),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    p.add_argument("--vocabulary", default="", help="vocabulary file (default: the shipped one)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a LoopConfig field, e.g. top_k=5 (repeatable)",
    )
    p.add_argument("--max-error-cm", type=float, default=10.0)
    p.add_argument("--max-error-deg", type=float, default=5.0)
    p.add_argument("--skip-tum", action="store_true")
    p.add_argument("--skip-timing", action="store_true", help="skip the 1,000-keyframe query timing")
    p.add_argument("--verbose", action="store_true", help="list every accepted loop")
    args = p.parse_args()

    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        kind = type(getattr(LoopConfig(), key))
        overrides[key] = (value.lower() == "true") if kind is bool else kind(value)
    cfg = dataclasses.replace(LoopConfig(vocabulary=args.vocabulary), **overrides)

    t0 = time.perf_counter()
    vocab = Vocabulary.load(cfg.vocabulary)
    first = time.perf_counter() - t0
    loads = []
    for _ in range(5):
        t0 = time.perf_counter()
        Vocabulary.load(cfg.vocabulary)
        loads.append(time.perf_counter() - t0)
    figures: dict = {
        "vocabulary": str(cfg.vocabulary or shipped_vocabulary_path().relative_to(REPO)),
        "vocab_words": vocab.n_words,
        "vocab_load_s": round(statistics.median(loads), 4),
        "vocab_load_s_first": round(first, 4),
    }

    loop_frames = keyframes_of(scene(0), rectify=False)
    syn = run_sequence(loop_frames, cfg, vocab, args.max_error_cm, args.max_error_deg, with_revisits=True)
    figures.update(
        {
            "revisit_recall": round(syn.n_revisits_found / max(1, syn.n_queries_with_revisit), 3),
            "revisit_recall_one_sided": round(
                syn.n_one_sided_revisits_found / max(1, syn.n_queries_with_one_sided_revisit), 3
            ),
            "false_loops_synthetic": syn.n_false,
            "synthetic_keyframes": syn.n_keyframes,
            "synthetic_queries_with_revisit": syn.n_queries_with_revisit,
            "synthetic_revisits_found": syn.n_revisits_found,
            "synthetic_queries_with_one_sided_revisit": syn.n_queries_with_one_sided_revisit,
            "synthetic_one_sided_revisits_found": syn.n_one_sided_revisits_found,
            "synthetic_loop_keyframes": syn.n_loop_keyframes,
            "synthetic_detections": syn.n_detections,
            "synthetic_pose_error_cm_max": round(max(syn.errors_cm, default=0.0), 2),
            "describe_ms": round(statistics.median(syn.describe_ms), 2),
            "detect_ms": round(statistics.median(syn.detect_ms), 2),
            "detect_ms_max": round(max(syn.detect_ms), 2),
        }
    )
    if args.verbose:
        print("synthetic loops:", json.dumps(syn.detections, indent=1), file=sys.stderr)

    tum_path = SHARED_DATA / "tum_fr1_xyz_300"
    if args.skip_tum:
        pass
    elif not (tum_path / "rgb.txt").is_file():
        print(
            f"TUM data not found at {tum_path} (set NEB_SLAM_SHARED_DATA): false_loops_tum not measured",
            file=sys.stderr,
        )
    else:
        tum = run_sequence(
            keyframes_of(tum_path, rectify=True), cfg, vocab, args.max_error_cm, args.max_error_deg, with_revisits=False
        )
        figures.update(
            {
                "false_loops_tum": tum.n_false,
                "tum_keyframes": tum.n_keyframes,
                "tum_detections": tum.n_detections,
                "tum_loop_keyframes": tum.n_loop_keyframes,
                "tum_loop_keyframes_unscored": tum.n_unscored,
                "tum_pose_error_cm_median": round(statistics.median(tum.errors_cm), 2) if tum.errors_cm else None,
                "tum_pose_error_cm_max": round(max(tum.errors_cm), 2) if tum.errors_cm else None,
                "tum_pose_error_deg_max": round(max(tum.errors_deg), 2) if tum.errors_deg else None,
                "tum_detect_ms": round(statistics.median(tum.detect_ms), 2),
            }
        )
        if args.verbose:
            print("TUM loops:", json.dumps(tum.detections, indent=1), file=sys.stderr)

    if not args.skip_timing:
        figures.update(query_time_1000(cfg, vocab))
    figures.update(
        {"config": dataclasses.asdict(cfg), "load_average": round(os.getloadavg()[0], 2), "cpus": os.cpu_count()}
    )
    print(json.dumps(figures, indent=2))
    record("place_recognition", figures, args.json)


if __name__ == "__main__":
    main()
