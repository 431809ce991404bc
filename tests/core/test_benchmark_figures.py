"""The figures ``benchmarks/slam.py`` reads back from a run directory (hand-made timings and loops)."""

import importlib.util
from pathlib import Path

from neb_slam_core.io.run_dir import TIMINGS_COLUMNS, TIMINGS_FILE

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "slam.py"


def _bench_module():
    spec = importlib.util.spec_from_file_location("bench_slam", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_loop_and_speed_figures(tmp_path):
    (tmp_path / TIMINGS_FILE).write_text(
        ",".join(TIMINGS_COLUMNS) + "\n"
        "0,1,0.0,30.0,8000.0,12.0,8042.0,1,0,1,1.0,1,\n"
        "1,2,200.0,5.0,0.0,0.0,205.0,0,,1,0.0,1,\n"
        "2,3,210.0,5.0,1100.0,11000.0,12315.0,1,,1,0.0,1,\n"
        "3,4,190.0,5.0,0.0,0.0,195.0,0,,1,0.0,1,\n"
    )
    # metrics.json's loop figures: loop work (12 + 0 + 11000 + 0) ms over 4 frames, 2 loops applied
    metrics = {"n_loops_applied": 2, "loop_ms_mean": (12.0 + 11000.0) / 4}
    figures = _bench_module().loop_and_speed_figures(tmp_path, metrics)
    # the first frame's total 8042 ms
    assert figures == {"loops_applied": 2, "loop_s_per_frame": 2.753, "first_frame_s": 8.04}


def test_loop_and_speed_figures_without_timings(tmp_path):
    assert _bench_module().loop_and_speed_figures(tmp_path, {"n_loops_applied": 0, "loop_ms_mean": 0.0}) == {}
