"""`make demo`: the embedded default.

Generates the default synthetic scene (once) into bags/ and converts it to a ROS 2 bag (once), then
replays the bag through the node suite as separate processes over DDS (mapper, loop_closer, tracker,
bag_replay in lockstep; see neb_slam_ros/suite.py), and prints ATE, blocks, parameter MB, fps and
where the results are. The last line printed is the run directory (trajectory.txt, groundtruth.txt, mesh.ply, map.pt,
metrics.json, plots, logs/).

    make demo                                  # the default synthetic scene, config synthetic
    make demo BAG=bags/fr1_xyz CONFIG=tum      # any converted bag
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src" / "neb_slam_ros"))  # the ROS package is colcon-built, not pip-installed

from neb_slam_core.cli.main import main as neb_slam  # noqa: E402


def run(argv: list[str]) -> None:
    print("$ neb-slam " + " ".join(argv), flush=True)
    rc = neb_slam(argv)
    if rc:
        sys.exit(rc)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="bags/demo_scene", help="where the synthetic scene folder goes")
    p.add_argument("--bag", default="bags/demo_scene_bag", help="the bag to replay (made from --scene when missing)")
    p.add_argument("--config", default="synthetic", help="engine config preset or YAML file")
    p.add_argument("--count", type=int, default=0, help="frames to replay (0: all)")
    p.add_argument("--out", type=Path, help="run directory (default runs/demo-<bag>-<date>-<time>)")
    args = p.parse_args()
    scene, bag = REPO / args.scene, REPO / args.bag

    if not (bag / "metadata.yaml").is_file():
        if args.bag != p.get_default("bag"):
            print(f"demo: bag {args.bag} not found (convert a dataset with `neb-slam convert`)", file=sys.stderr)
            return 2
        run(["synth", str(scene), "--preset", "default"])
        run(["convert", "tum", str(scene), str(bag), "--depth", "32FC1"])
    else:
        print(f"bag already there: {bag.relative_to(REPO) if bag.is_relative_to(REPO) else bag}")

    # a private, local DDS graph unless the user chose one
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from neb_slam_ros.suite import launch

    out = args.out or REPO / time.strftime(f"runs/demo-{bag.name}-%Y%m%d-%H%M%S")
    print(
        f"replaying {bag.name} through mapper + loop_closer + tracker + bag_replay (lockstep, config {args.config}); "
        f"process logs in {out / 'logs'}",
        flush=True,
    )
    result = launch(bag, out, args.config, args.count)
    m = result.metrics
    bad = {k: v for k, v in result.exit_codes.items() if v != 0}

    def rel(path: Path) -> str:
        return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)

    print()
    print("demo results")
    if "ate_rmse_cm" in m:
        print(f"  ATE RMSE            {m['ate_rmse_cm']:.3f} cm ({m.get('n_poses')} poses)")
    print(f"  blocks / parameters {m.get('n_blocks')} / {m.get('param_mb', float('nan')):.3f} MB")
    print(
        f"  frames / fps        {m.get('n_frames')} / {m.get('fps', float('nan')):.3f} frames per second "
        f"({result.wall_s:.0f} s)"
    )
    for name in (
        "trajectory.txt",
        "groundtruth.txt",
        "mesh.ply",
        "map.pt",
        "metrics.json",
        "trajectory.png",
        "ate_over_time.png",
    ):
        if (out / name).is_file():
            print(f"  {name:<19} {rel(out / name)}")
    if (scene / "mesh.ply").is_file() and args.bag == p.get_default("bag"):
        print(
            f"  ground-truth mesh   {rel(scene / 'mesh.ply')}  "
            f"(neb-slam eval {rel(out)} --gt-mesh {rel(scene / 'mesh.ply')})"
        )
    if bad:
        print(f"  non-zero exits      {bad}; see {rel(out / 'logs')}", file=sys.stderr)
    print(rel(out))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
