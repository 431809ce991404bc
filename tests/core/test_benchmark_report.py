"""Benchmark results: the stamp ``benchmarks/common.py`` adds, and the tables ``benchmarks/report.py`` renders
(hand-made result files, values worked out by hand)."""

import importlib.util
import json
import os
import re
import sys
from datetime import UTC, datetime
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def _module(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


def _result(folder: Path, name: str, figures: dict, stamp: dict) -> None:
    (folder / name).write_text(json.dumps({**figures, "stamp": stamp}))


def test_recorded_paths_inside_the_repository_are_relative(tmp_path):
    common = _module("common")
    inside = str(common.REPO / "runs" / "x" / "trajectory.txt")
    figures = {"trajectory": inside, "runs": [{"trajectory": inside}], "bag": "/elsewhere/bag", "n": 3}
    path = common.record("live", figures, None, results_dir=tmp_path)
    data = json.loads(path.read_text())
    assert data["trajectory"] == os.path.join("runs", "x", "trajectory.txt")
    assert data["runs"] == [{"trajectory": os.path.join("runs", "x", "trajectory.txt")}]
    assert data["bag"] == "/elsewhere/bag" and data["n"] == 3  # outside the repository: as given


def test_record_stamps_results_and_the_json_copy(tmp_path):
    common = _module("common")
    figures = {"ate_rmse_cm": 1.5, "first_frame_s": 9.65, "n_blocks": 1}
    now = datetime(2025, 1, 2, 3, 4, 5, tzinfo=UTC)
    copy = tmp_path / "tum.json"
    path = common.record("slam-tum", figures, copy, results_dir=tmp_path / "results", now=now)

    assert path == tmp_path / "results" / "slam-tum-20250102-030405.json"
    assert copy.read_text() == path.read_text()
    data = json.loads(path.read_text())
    stamp = data.pop("stamp")
    assert data == figures  # the figures themselves are unchanged
    assert stamp["benchmark"] == "slam-tum"
    assert stamp["date_utc"] == "2025-01-02T03:04:05Z"
    assert re.fullmatch(r"[0-9a-f]{4,40}(-dirty)?|unknown", stamp["commit"])
    assert len(stamp["load_average"]) == 3
    assert stamp["cpus"] == os.cpu_count()
    assert stamp["first_frame_s"] == 9.65

    # a second run within the same second does not overwrite the first; no first_frame_s, none stamped
    again = common.record("tracking", {"track_ms": 204.0}, None, results_dir=tmp_path / "results", now=now)
    assert again.name == "tracking-20250102-030405.json"
    assert "first_frame_s" not in json.loads(again.read_text())["stamp"]
    third = common.record("tracking", {"track_ms": 205.0}, None, results_dir=tmp_path / "results", now=now)
    assert third.name == "tracking-20250102-030405-2.json"


def test_report_renders_one_table_newest_first(tmp_path):
    report = _module("report")
    _result(
        tmp_path,
        "slam-tum-20250101-100000.json",
        {"config": "tum", "frames": 294, "ate_rmse_cm": 1.6012, "s_per_frame": 0.63, "n_blocks": 1, "param_mb": 3.556},
        {
            "benchmark": "slam-tum",
            "commit": "abc1234",
            "date_utc": "2025-01-01T10:00:00Z",
            "load_average": [1.5, 1.25, 1.0],
            "cpus": 2,
            "argv": ["tum", "--json", "tum.json"],
        },
    )
    _result(
        tmp_path,
        "slam-tum-20250103-083000.json",
        {
            "config": "tum",
            "frames": 100,
            "ate_rmse_cm": 1.58,
            "s_per_frame": 0.71,
            "first_frame_s": 9.62,
            "n_blocks": 1,
            "param_mb": 3.556,
        },
        {
            "benchmark": "slam-tum",
            "commit": "def5678-dirty",
            "date_utc": "2025-01-03T08:30:00Z",
            "load_average": [2.0, 1.75, 1.5],
            "cpus": 2,
            "argv": ["tum", "--frames", "100"],
            "first_frame_s": 9.62,
        },
    )

    text = report.render(report.load_results(tmp_path))
    lines = text.splitlines()
    start = lines.index("## slam-tum")
    table = [line for line in lines[start + 1 :] if line.startswith("|")]
    assert table == [
        "| date (UTC) | commit | load 1/5/15 min | CPUs | config | frames | ATE cm | s/frame | first frame s | blocks "
        "| MB | arguments |",
        "|" + "---|" * 12,
        "| 2025-01-03 08:30 | def5678-dirty | 2 / 1.75 / 1.5 | 2 | tum | 100 | 1.58 | 0.71 | 9.62 | 1 | 3.556 "
        "| `tum --frames 100` |",
        "| 2025-01-01 10:00 | abc1234 | 1.5 / 1.25 / 1 | 2 | tum | 294 | 1.601 | 0.63 |  | 1 | 3.556 | `tum` |",
    ]
    assert text.count("## ") == 1  # one benchmark, one table

    out = tmp_path / "docs" / "benchmarks.md"
    assert report.main(["--results", str(tmp_path), "--out", str(out)]) == 0
    assert out.read_text() == text
