"""Render ``docs/benchmarks.md`` from the stamped results in ``benchmarks/results/*.json``.

One table per benchmark (``slam-tum``, ``tracking``, ...), one row per result file, newest first: its
date (UTC), commit, the machine's load average and CPU count when it ran, the benchmark's headline
figures (:data:`COLUMNS`, chosen per benchmark family from the keys its script writes) and the script's
arguments. A benchmark without an entry in :data:`COLUMNS` gets its scalar figures. Columns that no
row of a table has are left out.

Usage::

    .venv/bin/python benchmarks/report.py                    # benchmarks/results -> docs/benchmarks.md
    .venv/bin/python benchmarks/report.py --results DIR --out FILE
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
OUT = REPO / "docs" / "benchmarks.md"
STAMP_KEY = "stamp"  # as benchmarks/common.py writes it
_NAME_RE = re.compile(r"^(?P<benchmark>.+)-(?P<date>\d{8})-(?P<time>\d{6})(?:-\d+)?\.json$")


def fmt(value) -> str:
    """A figure as table text: integers as they are, floats to 4 significant digits (no exponent from
    0.001 to 9999), lists comma-separated, dicts ``key: value`` separated by ``;``, None empty."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if value != value:  # NaN
            return "nan"
        if value == 0 or 1e-3 <= abs(value) < 1e4:
            text = f"{value:.4g}"
            return f"{value:.0f}" if "e" in text else text
        return f"{value:.2e}"
    if isinstance(value, (list, tuple)):
        return ", ".join(fmt(v) for v in value)
    if isinstance(value, dict):
        return "; ".join(f"{k}: {fmt(v)}" for k, v in value.items())
    return str(value).replace("|", "\\|").replace("\n", " ")


def _name_only(value) -> str:
    return Path(str(value)).name if value else ""


def _ends(value) -> str:
    """pose_graph_edges' ``ends``: frame: ATE with tracked edges / with registrations."""
    if not isinstance(value, dict):
        return fmt(value)
    return "; ".join(
        f"{frame}: {fmt(v.get('ate_cm_tracked_edges'))} / {fmt(v.get('ate_cm_with_registrations'))}"
        for frame, v in value.items()
    )


def _interruption(value) -> str:
    """relocalisation's ``gap`` / ``black``: frames until recovery; ATE after it / uninterrupted (ratio)."""
    if not isinstance(value, dict):
        return fmt(value)
    return (
        f"{fmt(value.get('recovered_after'))}; {fmt(value.get('ate_cm_after'))} / "
        f"{fmt(value.get('ate_cm_after_uninterrupted'))} ({fmt(value.get('ratio'))})"
    )


def _updates(value) -> str:
    """map_updates' per-source figures: MB/s whole float32 -> as sent; the tracked poses' largest difference."""
    if not isinstance(value, dict):
        return fmt(value)
    return (
        f"{fmt(value.get('mb_per_s_old'))} -> {fmt(value.get('mb_per_s_new'))} MB/s; "
        f"{fmt(value.get('pose_diff_cm_max'))} cm"
    )


def _words(value) -> str:
    return " ".join(str(v) for v in value) if isinstance(value, (list, tuple)) else fmt(value)


@dataclass(frozen=True)
class Column:
    key: str
    header: str
    format: Callable[[object], str] = fmt


C = Column
#: benchmark family (the name before its first ``-``) -> headline columns
COLUMNS: dict[str, list[Column]] = {
    "slam": [
        C("config", "config"),
        C("frames", "frames"),
        C("ate_rmse_cm", "ATE cm"),
        C("rpe_frame_trans_cm", "frame-to-frame cm"),
        C("rpe_frame_rot_deg", "frame-to-frame deg"),
        C("s_per_frame", "s/frame"),
        C("track_s_per_frame", "tracking s/frame"),
        C("map_s_per_frame", "mapping s/frame"),
        C("loop_s_per_frame", "loop s/frame"),
        C("loops_applied", "loops applied"),
        C("first_frame_s", "first frame s"),
        C("n_tracking_failures", "tracking failures"),
        C("n_blocks", "blocks"),
        C("param_mb", "MB"),
        C("accuracy_cm", "accuracy cm"),
        C("completion_cm", "completion cm"),
        C("completion_ratio_pct", "< 5 cm %"),
        C("recon_floor_cm", "floor cm"),
        C("recon_points", "points per mesh"),
    ],
    "tracking": [
        C("normal_equations_ms_closed", "GN system ms, closed form"),
        C("normal_equations_ms_fd", "forward differences"),
        C("normal_equations_ms_autograd", "autograd"),
        C("fd_over_closed", "fd / closed"),
        C("autograd_over_closed", "autograd / closed"),
        C("max_rel_diff_H_closed", "closed vs autograd (rel.)"),
        C("evaluate_pose_ms", "objective ms"),
        C("track_ms", "tracking ms/frame"),
        C("track_steps", "steps"),
        C("threads", "threads"),
    ],
    "sample_skip": [
        C("skip_behind_m", "skip behind m"),
        C("evaluated_share", "samples evaluated"),
        C("map_step_ms_skip", "mapping step ms"),
        C("map_step_ms_all", "every sample"),
        C("map_step_ratio", "ratio"),
        C("objective_rel_diff", "objective rel. diff"),
        C("track_ms_skip", "tracking ms/frame"),
        C("track_ms_all", "every sample"),
        C("track_ratio", "ratio"),
        C("pose_gap_mm", "pose gap mm"),
        C("threads", "threads"),
    ],
    "scaling": [
        C("n_blocks_start", "blocks"),
        C("n_blocks", "blocks (many)"),
        C("track_ms_one_block", "ms/frame, one block"),
        C("track_ms_many_blocks", "many blocks"),
        C("ratio", "ratio"),
        C("tracker_ms_one_block", "tracker ms, one block"),
        C("tracker_ms_many_blocks", "many blocks"),
        C("tracker_ratio", "tracker ratio"),
        C("threads", "threads"),
    ],
    "map_fit": [
        C("iterations", "iterations"),
        C("n_blocks", "blocks"),
        C("param_mb", "MB"),
        C("held_out_depth_l1_cm", "held-out depth L1 cm"),
        C("accuracy_cm", "accuracy cm"),
        C("completion_cm", "completion cm"),
        C("completion_ratio_pct", "< 5 cm %"),
        C("seam_step_max_cm", "seam step max cm"),
        C("seam_step_p99_cm", "seam p99 cm"),
        C("other_step_p99_cm", "elsewhere p99 cm"),
        C("fit_s_per_iteration", "s/iteration"),
    ],
    "loop_ablation": [
        C("config", "config"),
        C("frames", "frames"),
        C("extra_args", "engine args", _words),
        C("ate_cm_without", "ATE cm without"),
        C("ate_cm_with", "with"),
        C("ate_ratio", "ratio"),
        C("acc_cm_without", "accuracy cm without"),
        C("acc_cm_with", "with"),
        C("comp_ratio_pct_without", "< 5 cm % without"),
        C("comp_ratio_pct_with", "with"),
        C("loops_detected", "loops detected"),
        C("loops_applied", "applied"),
        C("revisit_recall", "revisit recall"),
        C("false_loops_synthetic", "false loops (synthetic)"),
        C("false_loops_tum", "false loops (TUM)"),
    ],
    "place_recognition": [
        C("vocab_words", "words"),
        C("vocab_load_s", "vocabulary load s"),
        C("query_ms_1000", "query ms (1000 keyframes)"),
        C("describe_ms", "describe ms"),
        C("detect_ms", "detect ms"),
        C("revisit_recall", "revisit recall"),
        C("revisit_recall_one_sided", "one-sided"),
        C("false_loops_synthetic", "false (synthetic)"),
        C("false_loops_tum", "false (TUM)"),
        C("tum_detections", "TUM detections"),
    ],
    "pose_graph_edges": [
        C("n_keyframes", "keyframes"),
        C("ate_cm_before", "ATE cm"),
        C("ate_cm_keyframes_true", "keyframes true"),
        C("ends", "by end: tracked edges / with registrations", _ends),
        C("registration_error_cm_mean", "registration error cm"),
        C("tracked_error_cm_mean", "tracked error cm"),
        C("register_ms_mean", "register ms"),
    ],
    "ros_suite": [
        C("bag", "bag", _name_only),
        C("config", "config"),
        C("n_frames", "frames"),
        C("fps_separate", "fps, separate"),
        C("fps_one_process", "fps, one process"),
        C("ratio", "ratio"),
        C("ate_cm_separate", "ATE cm, separate"),
        C("ate_cm_one_process", "one process"),
    ],
    "ros_outputs": [
        C("blocks", "blocks"),
        C("mesh_old_ms", "mesh ms, reference"),
        C("mesh_new_all_ms", "all blocks changed"),
        C("mesh_all_ratio", "ratio"),
        C("mesh_new_changed_ms", "some changed"),
        C("mesh_new_changed_blocks", "re-extracted"),
        C("mesh_changed_ratio", "ratio"),
        C("mesh_conversion_ratio", "markers alone, ratio"),
        C("frames", "path frames"),
        C("path_old_ms_per_frame", "path ms/frame, reference"),
        C("path_new_ms_per_frame", "new"),
        C("path_ratio", "ratio"),
        C("map_update_mb_per_s_old", "map_update MB/s demo, whole float32"),
        C("map_update_mb_per_s_new", "as sent"),
        C("map_update_tum_mb_per_s_old", "TUM, whole float32"),
        C("map_update_tum_mb_per_s_new", "as sent"),
        C("map_update_pose_diff_cm_max", "tracked pose difference cm, demo"),
        C("map_update_tum_pose_diff_cm_max", "TUM"),
    ],
    "map_updates": [
        C("demo", "demo: map_update whole float32 -> as sent; tracked pose difference", _updates),
        C("tum", "TUM fr1_xyz", _updates),
    ],
    "loop_truth": [
        C("overrides", "overrides"),
        C("frames", "frames"),
        C("ate_cm", "ATE cm"),
        C("bands", "per band of fit RMS (px): events, applied, mean gain / measurement error"),
    ],
    "soak": [
        C("bag", "bag", _name_only),
        C("config", "config"),
        C("frames", "frames"),
        C("keyframes", "keyframes"),
        C("rss_mb_per_keyframe", "RSS MB/keyframe"),
        C("stores_kb_per_keyframe", "stores KB/keyframe"),
        C("store_kb_per_keyframe", "per store KB/keyframe"),
        C("time_ratio_last_vs_early", "time last/early"),
        C("ate_cm", "ATE cm"),
        C("tracking_failures", "tracking failures"),
        C("loops_applied", "loops applied"),
    ],
    "relocalisation": [
        C("config", "config"),
        C("frames", "frames"),
        C("stride", "stride"),
        C("gap", "frames left out: recovered after; ATE cm after / uninterrupted (ratio)", _interruption),
        C("black", "frames black: the same", _interruption),
        C("uninterrupted", "uninterrupted", lambda v: fmt(v.get("ate_cm")) if isinstance(v, dict) else fmt(v)),
    ],
    "encoding": [
        C("fast_fwd_ms", "fast fwd ms"),
        C("fast_fwd_bwd_ms", "fwd+bwd (table)"),
        C("fast_fwd_bwd_points_ms", "fwd+bwd (points)"),
        C("reference_fwd_bwd_ms", "reference fwd+bwd"),
        C("floor_gather_ms", "gather floor"),
        C("ratio_reference_over_fast", "reference / fast"),
        C("ratio_fast_fwd_over_floor", "fast fwd / floor"),
        C("block_mb_t15", "MB/block T=2^15"),
        C("block_mb_t14", "T=2^14"),
        C("threads", "threads"),
    ],
}
#: the script that writes each benchmark family
SCRIPTS = {family: f"benchmarks/{family}.py" for family in COLUMNS}


@dataclass
class Result:
    benchmark: str
    date_utc: str  # ISO 8601, or '' when unknown
    commit: str
    load_average: list
    cpus: int | None
    argv: list
    figures: dict
    file: str


def load_result(path: Path) -> Result:
    """One result file; a file without a stamp takes its benchmark name and date from its file name."""
    data = json.loads(path.read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object")
    st = data.get(STAMP_KEY) or {}
    figures = {k: v for k, v in data.items() if k != STAMP_KEY}
    m = _NAME_RE.match(path.name)
    benchmark = st.get("benchmark") or (m.group("benchmark") if m else path.stem)
    date = st.get("date_utc") or ""
    if not date and m:
        d, t = m.group("date"), m.group("time")
        date = f"{d[:4]}-{d[4:6]}-{d[6:]}T{t[:2]}:{t[2:4]}:{t[4:]}Z"
    load = st.get("load_average")
    return Result(
        benchmark,
        date,
        st.get("commit") or "",
        load if isinstance(load, list) else [load],
        st.get("cpus"),
        list(st.get("argv") or []),
        figures,
        path.name,
    )


def load_results(folder: Path) -> list[Result]:
    return [load_result(p) for p in sorted(Path(folder).glob("*.json"))]


def columns_for(benchmark: str, rows: list[Result]) -> list[Column]:
    """The benchmark family's columns that at least one row has (its scalar figures when none)."""
    spec = COLUMNS.get(benchmark.split("-")[0], [])
    present = [c for c in spec if any(r.figures.get(c.key) is not None for r in rows)]
    if present:
        return present
    keys: list[str] = []
    for r in rows:
        keys += [k for k, v in r.figures.items() if isinstance(v, (int, float)) and k not in keys]
    return [Column(k, k) for k in keys]


def _args(argv: list) -> str:
    """The script's arguments without ``--json FILE`` (where a copy went is not what was measured)."""
    shown, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--json":
            skip = True
        elif not a.startswith("--json="):
            shown.append(str(a))
    return f"`{' '.join(shown)}`" if shown else ""


def table(benchmark: str, rows: list[Result]) -> list[str]:
    rows = sorted(rows, key=lambda r: (r.date_utc, r.file), reverse=True)
    cols = columns_for(benchmark, rows)
    head = ["date (UTC)", "commit", "load 1/5/15 min", "CPUs"] + [c.header for c in cols] + ["arguments"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        date = r.date_utc.replace("T", " ").rstrip("Z")[:16]
        cells = [date, r.commit, " / ".join(fmt(v) for v in r.load_average), fmt(r.cpus)]
        cells += [c.format(r.figures.get(c.key)) for c in cols]
        cells.append(_args(r.argv))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def render(results: list[Result]) -> str:
    """The whole ``docs/benchmarks.md``."""
    out = [
        "# Benchmark results",
        "",
        "Generated by `benchmarks/report.py` from `benchmarks/results/*.json`; do not edit by hand. "
        "What each benchmark measures and how to run it: [evaluation.md](evaluation.md#reproducing-the-figures).",
        "",
    ]
    by_name: dict[str, list[Result]] = {}
    for r in results:
        by_name.setdefault(r.benchmark, []).append(r)
    if not by_name:
        out += ["No results yet.", ""]
    for name in sorted(by_name):
        script = SCRIPTS.get(name.split("-")[0])
        out += [f"## {name}", ""]
        if script:
            out += [f"`{script}`", ""]
        out += table(name, by_name[name]) + [""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", type=Path, default=RESULTS, help="folder of result files (default benchmarks/results)")
    p.add_argument("--out", type=Path, default=OUT, help="the Markdown file to write (default docs/benchmarks.md)")
    args = p.parse_args(argv)
    text = render(load_results(args.results))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
