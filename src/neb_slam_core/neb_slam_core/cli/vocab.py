"""Build or inspect the bag-of-words vocabulary of loop closure (ORB words, TF-IDF weights).

``train`` renders frames of the project's own synthetic scenes in memory (presets and seeds below;
no files are written but the vocabulary), extracts ORB features from them and builds a vocabulary tree
of branching K and depth L (at most K^L words) with TF-IDF weights. The result is a function of the
options: the same options give the same file. Real data is for evaluating a vocabulary, not for
training the shipped one. ``info`` prints what a vocabulary file holds and how long it takes to load.

The vocabulary shipped in the package (``neb_slam_core/loop/data/orb_vocabulary.npz``) was built with
the defaults:

    neb-slam vocab train src/neb_slam_core/neb_slam_core/loop/data/orb_vocabulary.npz

Examples:
    neb-slam vocab train my_vocab.npz --scenes 12 --frames 30 --k 10 --depth 5
    neb-slam vocab info                       # the shipped vocabulary
    neb-slam vocab info my_vocab.npz
"""

from __future__ import annotations

import argparse
import logging
import time

HELP = "train or inspect the ORB bag-of-words vocabulary (loop closure)"

log = logging.getLogger(__name__)

#: scene presets rendered for training, used in turn (scene i: preset i mod len, seed first_seed + i)
TRAIN_PRESETS = ("default", "corridor")


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT like 640x480, got {text!r}") from None


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="vocab_command", required=True, metavar="ACTION")
    t = sub.add_parser(
        "train",
        help="build a vocabulary from synthetic renders",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    t.add_argument("out", metavar="OUT", help="vocabulary file to write (.npz)")
    t.add_argument(
        "--scenes",
        type=_positive,
        default=8,
        metavar="N",
        help=f"synthetic scenes rendered, presets {', '.join(TRAIN_PRESETS)} in turn (default: %(default)s)",
    )
    t.add_argument(
        "--frames",
        type=_positive,
        default=30,
        metavar="N",
        help="frames per scene, evenly spaced along its trajectory (default: %(default)s)",
    )
    t.add_argument(
        "--size",
        type=_size,
        default=(640, 480),
        metavar="WxH",
        help="render size (default: 640x480, the size of the usual RGB-D cameras)",
    )
    t.add_argument(
        "--scene-seed",
        type=int,
        default=1000,
        metavar="S",
        help="seed of the first scene; scene i uses S + i (default: %(default)s; the benchmarks "
        "evaluate on seeds 0..3, so keep them out)",
    )
    t.add_argument("--k", type=int, default=10, help="branching factor (default: %(default)s)")
    t.add_argument("--depth", type=int, default=4, help="tree depth L (default: %(default)s; K^L words at most)")
    t.add_argument("--seed", type=int, default=0, help="clustering seed (default: %(default)s)")
    t.add_argument(
        "--n-features",
        type=_positive,
        default=1000,
        metavar="N",
        help="ORB features per frame at most (default: %(default)s)",
    )
    t.add_argument(
        "--iterations",
        type=_positive,
        default=10,
        metavar="N",
        help="k-majority iterations per node at most (default: %(default)s)",
    )
    i = sub.add_parser("info", help="print what a vocabulary file holds")
    i.add_argument("path", nargs="?", default="", metavar="FILE", help="vocabulary file (default: the shipped one)")


def run(args: argparse.Namespace) -> int:
    return _train(args) if args.vocab_command == "train" else _info(args)


def _info(args: argparse.Namespace) -> int:
    import numpy as np

    from ..loop.vocabulary import Vocabulary, shipped_vocabulary_path

    t0 = time.perf_counter()
    vocab = Vocabulary.load(args.path)
    seconds = time.perf_counter() - t0
    leaves = vocab.children[:, 0] < 0
    print(f"file:        {args.path or shipped_vocabulary_path()}")
    print(f"tree:        k={vocab.branching}, L={vocab.depth}, {vocab.n_words} words, {vocab.n_nodes} nodes")
    print(
        f"idf:         {float(vocab.idf.min()):.3f}..{float(vocab.idf.max()):.3f}, "
        f"{int(np.sum(vocab.idf == 0))} words with weight 0"
    )
    print(f"leaves:      {int(leaves.sum())}")
    print(
        f"training:    {vocab.training.n_images} images, {vocab.training.n_descriptors} descriptors, "
        f"seed {vocab.training.seed}"
    )
    print(f"source:      {vocab.training.source}")
    print(f"load time:   {seconds * 1e3:.1f} ms")
    return 0


def _train(args: argparse.Namespace) -> int:
    from pathlib import Path

    from tqdm import tqdm

    from ..errors import ConfigError
    from ..loop.features import OrbExtractor, OrbParams
    from ..loop.vocabulary import train_vocabulary
    from ..synth.generate import build_sequence, resolve_spec
    from ..synth.render import Renderer

    if args.k < 2 or args.depth < 1 or args.k**args.depth > 10**7:
        raise ConfigError(f"vocab train: need --k >= 2, --depth >= 1 and k^depth <= 10^7, got {args.k}, {args.depth}")
    out = Path(args.out)
    extractor = OrbExtractor(OrbParams(n_features=args.n_features))
    t0 = time.perf_counter()
    descriptors = []
    n_frames = args.scenes * args.frames
    with tqdm(total=n_frames, desc="render + ORB", unit="frame") as bar:
        for s in range(args.scenes):
            preset = TRAIN_PRESETS[s % len(TRAIN_PRESETS)]
            spec = resolve_spec(preset, size=args.size, seed=args.scene_seed + s)
            seq = build_sequence(spec)
            renderer = Renderer.for_scene(seq.scene, spec.camera.intrinsics())
            poses = seq.trajectory.poses
            # evenly spaced frames, half a step in from both ends (a closed loop's last frame is its first)
            picks = ((len(poses) * (2 * i + 1)) // (2 * args.frames) for i in range(args.frames))
            for f in picks:
                feats = extractor(renderer.render(poses[f]).rgb)
                descriptors.append(feats.descriptors)
                bar.update(1)
    t_render = time.perf_counter() - t0
    n_desc = sum(len(d) for d in descriptors)
    print(
        f"{len(descriptors)} frames, {n_desc} ORB descriptors ({n_desc / max(1, len(descriptors)):.0f} per frame) "
        f"in {t_render:.0f} s"
    )
    source = (
        f"neb-slam vocab train: presets {'/'.join(TRAIN_PRESETS)} in turn, {args.scenes} scenes "
        f"(seeds {args.scene_seed}..{args.scene_seed + args.scenes - 1}), {args.frames} frames each at "
        f"{args.size[0]}x{args.size[1]}, ORB {args.n_features} features"
    )
    t1 = time.perf_counter()
    with tqdm(desc="clustering", unit="node") as bar:

        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        vocab = train_vocabulary(
            descriptors,
            branching=args.k,
            depth=args.depth,
            seed=args.seed,
            max_iterations=args.iterations,
            source=source,
            progress=progress,
        )
    vocab.save(out)
    print(
        f"{out}: {vocab.n_words} words (k={vocab.branching}, L={vocab.depth}), {vocab.n_nodes} nodes, "
        f"{out.stat().st_size / 1e6:.2f} MB; clustering {time.perf_counter() - t1:.0f} s"
    )
    return 0
