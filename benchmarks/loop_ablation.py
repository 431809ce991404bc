"""Loop closure on / off, as the paper's ablation table: ATE and reconstruction accuracy of two runs of
``neb-slam run`` on one synthetic loop that returns to its start, plus the place recognition figures.

The scene is the ``default`` synthetic preset (160x120, 300 frames, the route returns to its start;
generated once under ``.cache/scenes/``), with ``--noise`` the Kinect-like depth noise model. The two
runs differ in ``loop.enabled`` only (same config, same seed). Extra arguments after ``--`` go to both
runs (e.g. ``-- --seed 1`` for another realisation of the drift: the engine's random draws differ,
the scene stays; ``-- --set tracking.iterations=4`` to make tracking drift more).

Figures (JSON keys): ``ate_cm_with``, ``ate_cm_without``, ``ate_ratio`` (with / without; target at most
0.7), ``acc_cm_with``, ``acc_cm_without`` (accuracy of the mesh against the scene's, culled to the
cameras; target: not worse), ``comp_cm_*``, ``comp_ratio_pct_*``, ``loops_detected``, ``loops_applied``,
``s_per_frame_*``; and from ``benchmarks/place_recognition.py`` (run alongside, unless
``--skip-place-recognition``): ``revisit_recall``, ``false_loops_synthetic``, ``false_loops_tum``,
``query_ms_1000``, ``vocab_load_s``.

Usage::

    .venv/bin/python benchmarks/loop_ablation.py --noise --json loop_ablation.json
    .venv/bin/python benchmarks/loop_ablation.py --noise --skip-place-recognition -- --seed 1
    .venv/bin/python benchmarks/loop_ablation.py --noise -- --set tracking.iterations=4
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from common import record

from neb_slam_core.synth.generate import generate

REPO = Path(__file__).resolve().parents[1]


def run(source: Path, out: Path, loop: bool, config: str, frames: int | None, extra: list[str]) -> dict:
    cmd = [
        sys.executable,
        "-m",
        "neb_slam_core.cli.main",
        "run",
        str(source),
        "--config",
        config,
        "--out",
        str(out),
        "--set",
        f"loop.enabled={'true' if loop else 'false'}",
        *extra,
    ]
    if frames:
        cmd += ["--frames", str(frames)]
    print(f"loop closure {'on' if loop else 'off'}: {' '.join(cmd[2:])}", file=sys.stderr, flush=True)
    code = subprocess.run(cmd).returncode
    if code != 0 or not (out / "metrics.json").is_file():
        sys.exit(f"neb-slam run failed (exit code {code}); see its messages above")
    return json.loads((out / "metrics.json").read_text())


def main() -> None:
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--noise", action="store_true", help="the scene with Kinect-like depth noise")
    p.add_argument("--config", default="synthetic")
    p.add_argument("--frames", type=int, default=None, help="only the first N frames (the loop needs them all)")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="parent of the two run directories (default runs/loop-ablation-<date-time>)",
    )
    p.add_argument("--json", type=Path, default=None, help="a copy of the stamped figures (see benchmarks/results/)")
    p.add_argument("--skip-place-recognition", action="store_true")
    args = p.parse_args(argv)

    name = "default-noise" if args.noise else "default"
    source = generate("default", REPO / ".cache" / "scenes" / name, noise=args.noise, progress=True)
    out = args.out or REPO / "runs" / f"loop-ablation-{time.strftime('%Y%m%d-%H%M%S')}"
    load_before = os.getloadavg()[0]
    without = run(source, out / "without", False, args.config, args.frames, extra)
    with_ = run(source, out / "with", True, args.config, args.frames, extra)
    loops = json.loads((out / "with" / "loops.json").read_text())

    figures: dict = {
        "scene": name,
        "config": args.config,
        "extra_args": extra,
        "frames": with_["n_frames"],
        "ate_cm_with": with_.get("ate_rmse_cm"),
        "ate_cm_without": without.get("ate_rmse_cm"),
    }
    if figures["ate_cm_with"] is not None and figures["ate_cm_without"]:
        figures["ate_ratio"] = round(figures["ate_cm_with"] / figures["ate_cm_without"], 3)
    for key, short in (
        ("accuracy_cm", "acc_cm"),
        ("completion_cm", "comp_cm"),
        ("completion_ratio_pct", "comp_ratio_pct"),
        ("s_per_frame", "s_per_frame"),
    ):
        figures[f"{short}_with"] = with_.get(key)
        figures[f"{short}_without"] = without.get(key)
    figures.update(
        {
            "loops_detected": len(loops),
            "loops_applied": sum(e["applied"] for e in loops),
            "loops": [
                {
                    k: e[k]
                    for k in ("frame", "loop_frames", "score", "applied", "reason", "correction_cm", "correction_deg")
                }
                for e in loops
            ],
            "n_blocks_with": with_.get("n_blocks"),
            "n_blocks_without": without.get("n_blocks"),
            "load_average_before": round(load_before, 2),
            "run_dirs": [str(out / "without"), str(out / "with")],
        }
    )
    if not args.skip_place_recognition:
        pr_json = out / "place_recognition.json"
        code = subprocess.run(
            [sys.executable, str(REPO / "benchmarks" / "place_recognition.py"), "--json", str(pr_json)],
            stdout=subprocess.DEVNULL,
        ).returncode
        if code != 0:
            sys.exit(f"benchmarks/place_recognition.py failed (exit code {code})")
        pr = json.loads(pr_json.read_text())
        for key in ("revisit_recall", "false_loops_synthetic", "false_loops_tum", "query_ms_1000", "vocab_load_s"):
            figures[key] = pr.get(key)
    print(json.dumps(figures, indent=2))
    record(f"loop_ablation-{name}", figures, args.json)


if __name__ == "__main__":
    main()
