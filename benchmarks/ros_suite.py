"""The ROS node suite's speed: separate processes (mapper, tracker, bag_replay) against the one-process
``slam`` executable, on the same bag in lockstep, measured in one run.

Default bag: the first ``--frames`` (20) frames of the ``small`` synthetic preset (generated once under
``.cache/scenes/``), config ``ci``; ``--bag`` and ``--config`` replay anything else. Prints (and with
``--json`` writes) ``fps_separate``, ``fps_one_process`` (frames per second of the replay, from its first
frame to its last pose, first frame's map initialisation included; process start-up and the final
writing of files excluded), their ``ratio``, and each run's ATE RMSE (cm), which lockstep makes
equal. Every process talks on a random ROS domain on localhost only.

    .venv/bin/python benchmarks/ros_suite.py --json ros_suite.json
    .venv/bin/python benchmarks/ros_suite.py --bag bags/fr1_xyz --config tum --frames 60
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src" / "neb_slam_ros"))  # the ROS package is colcon-built, not pip-installed

from common import record  # noqa: E402

from neb_slam_ros.suite import _env, launch  # noqa: E402


def small_bag(frames: int) -> Path:
    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.io.bag import BagWriteOptions, write_bag
    from neb_slam_core.synth.generate import generate

    scene = REPO / ".cache" / "scenes" / "small"
    bag = REPO / ".cache" / "scenes" / f"small-bag-{frames}"
    if not (bag / "metadata.yaml").is_file():
        if not (scene / "scene.json").is_file():
            generate("small", scene, progress=False)
        ds = open_dataset(scene)
        write_bag(
            [ds[i] for i in range(min(frames, len(ds)))], bag, BagWriteOptions(depth_encoding="32FC1"), progress=False
        )
    return bag


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bag", type=Path, help="bag to replay (default: the small synthetic scene)")
    p.add_argument("--config", default="ci")
    p.add_argument("--frames", type=int, default=20, help="frames to replay")
    p.add_argument("--json", type=Path, help="a copy of the stamped figures (see benchmarks/results/)")
    args = p.parse_args()
    bag = args.bag or small_bag(args.frames)
    env = _env()
    env["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 200))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    figures: dict[str, object] = {"bag": str(bag), "config": args.config, "load_average_start": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as tmp:
        for name, one in (("separate", False), ("one_process", True)):
            t0 = time.perf_counter()
            run = launch(bag, Path(tmp) / name, args.config, args.frames, one_process=one, env=env)
            if any(code != 0 for code in run.exit_codes.values()):
                print(f"{name}: non-zero exit {run.exit_codes}", file=sys.stderr)
                return 1
            n = run.metrics["n_frames"]
            figures[f"fps_{name}"] = round(n / run.replay_s, 4)
            figures[f"wall_s_{name}"] = round(time.perf_counter() - t0, 1)
            figures[f"ate_cm_{name}"] = round(run.metrics["ate_rmse_cm"], 4)
            figures["n_frames"] = n
    figures["ratio"] = round(figures["fps_one_process"] / figures["fps_separate"], 3)
    print(json.dumps(figures, indent=2))
    record("ros_suite", figures, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
