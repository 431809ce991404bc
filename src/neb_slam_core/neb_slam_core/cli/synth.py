"""Generate a synthetic RGB-D sequence with ground truth (TUM layout) from a named scene preset.

Presets: ``default`` (multi-room demo, 160x120, 300 frames, loop), ``large`` (320x240, 600 frames,
loop through six rooms), ``small`` (one room, 96x72, 60 frames), ``corridor`` (a 28 m corridor, 500
frames, no loop). The folder holds rgb/, depth/ (16-bit, metres x 5000), rgb.txt, depth.txt,
groundtruth.txt, intrinsics.json, mesh.ply and scene.json, and opens with every command that reads a
TUM folder. When OUT_DIR already holds the same scene with the same options, nothing is redone.

Example:
    neb-slam synth data/synth_default
    neb-slam synth data/synth_large --preset large --size 640x480 --seed 3 --noise
"""

from __future__ import annotations

import argparse
import json
import time

HELP = "generate a synthetic RGB-D sequence with ground-truth poses and mesh"


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT like 320x240, got {text!r}") from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    from ..synth.presets import preset_names

    p.add_argument("out_dir", metavar="OUT_DIR", help="folder to write (created if missing)")
    p.add_argument("--preset", default="default", choices=preset_names(), help="scene preset (default: %(default)s)")
    p.add_argument("--frames", type=int, default=None, metavar="N", help="number of frames (default: the preset's)")
    p.add_argument(
        "--size", type=_size, default=None, metavar="WxH", help="image size, e.g. 320x240 (default: the preset's)"
    )
    p.add_argument("--seed", type=int, default=None, metavar="S", help="scene seed (default: the preset's, 0)")
    p.add_argument("--noise", action="store_true", help="apply the Kinect-like depth noise model")
    p.add_argument("--force", action="store_true", help="regenerate even when OUT_DIR already holds this scene")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from ..synth.generate import SCENE_FILE, generate, is_complete, resolve_spec

    spec = resolve_spec(
        args.preset, n_frames=args.frames, size=args.size, seed=args.seed, noise=True if args.noise else None
    )
    from pathlib import Path

    out = Path(args.out_dir)
    if not args.force and is_complete(out, spec):
        print(
            f"{out}: already holds scene '{spec.name}' (seed {spec.seed}, {spec.trajectory.n_frames} frames, "
            f"{spec.camera.width}x{spec.camera.height}); nothing to do (--force regenerates)"
        )
        return 0
    t0 = time.perf_counter()
    generate(spec, out, force=args.force, progress=not args.no_progress)
    seconds = time.perf_counter() - t0
    meta = json.loads((out / SCENE_FILE).read_text())
    size = meta["bounds_m"]["size"]
    tr = meta["trajectory"]
    print(f"{out}: scene '{spec.name}' seed {spec.seed}{' with depth noise' if spec.noise.enabled else ''}")
    print(
        f"  frames:     {meta['n_frames']} at {spec.camera.width}x{spec.camera.height} "
        f"({seconds:.1f} s, {meta['n_frames'] / seconds:.1f} frames/s)"
    )
    print(
        f"  scene:      {size[0]:.2f} x {size[1]:.2f} x {size[2]:.2f} m, {len(meta['mesh']['spaces'])} spaces, "
        f"{meta['mesh']['render_faces']} faces"
    )
    print(
        f"  trajectory: {tr['length_m']:.1f} m, {'loop' if tr['loop'] else 'open'}, {100 * tr['step_m_mean']:.1f} cm "
        f"and at most {tr['rotation_deg_per_frame_max']:.1f} deg per frame, clearance >= {tr['min_clearance_m']:.2f} m"
    )
    print("  files:      rgb/ depth/ rgb.txt depth.txt groundtruth.txt intrinsics.json mesh.ply scene.json")
    return 0
