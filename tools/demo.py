"""`make demo`: the embedded default.

Generates the default synthetic scene (once) into bags/, converts it to a ROS 2 bag (once), and prints
what it made and where. Later stages of the product (the SLAM run over the node suite) extend this
script; it stays the single entry point of `make demo`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from neb_slam_core.cli.main import main as neb_slam

REPO = Path(__file__).resolve().parents[1]


def run(argv: list[str]) -> None:
    print("$ neb-slam " + " ".join(argv), flush=True)
    rc = neb_slam(argv)
    if rc:
        sys.exit(rc)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="bags/demo_scene", help="where the synthetic scene folder goes")
    p.add_argument("--bag", default="bags/demo_scene_bag", help="where its ROS 2 bag goes")
    args = p.parse_args()
    scene, bag = REPO / args.scene, REPO / args.bag

    run(["synth", str(scene), "--preset", "default"])
    if (bag / "metadata.yaml").is_file():
        print(f"bag already there: {bag.relative_to(REPO)} (delete it to convert again)")
    else:
        run(["convert", "tum", str(scene), str(bag), "--depth", "32FC1"])

    info = json.loads((scene / "scene.json").read_text()) if (scene / "scene.json").is_file() else {}
    print()
    print("demo results")
    print(f"  synthetic scene (TUM layout): {scene.relative_to(REPO)}/  (rgb/, depth/, groundtruth.txt, intrinsics.json)")
    print(f"  ground-truth mesh:            {(scene / 'mesh.ply').relative_to(REPO)}")
    if info:
        print(f"  scene info:                   {(scene / 'scene.json').relative_to(REPO)}")
    print(f"  ROS 2 bag:                    {bag.relative_to(REPO)}/")
    print(bag.relative_to(REPO))
    return 0


if __name__ == "__main__":
    sys.exit(main())
