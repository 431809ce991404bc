"""Speed of the encodings and decoders (the hot kernels): fast C++ paths vs plain-torch references (and,
for the hash grid, vs a bare gather).

Measures, for one block with the paper's grid (16 levels x 2 features, T = 2^15), on 44,032 points
(1024 rays x 43 samples, one tracking iteration) and 110,080 points (2560 rays x 43 samples, one mapping
iteration):

- fast forward; fast forward+backward with the table gradient (mapping); fast forward+backward with the
  point gradient only (tracking); the plain-torch reference forward+backward (table gradient);
- the memory-bound floor: a bare ``index_select`` of as many table rows as the encoding looks up
  (N x 16 levels x 8 corners rows of 2 floats) from a table of the same size, with random rows and with
  the encoding's own rows (same locality).

- the one-blob encoding of the same points in world metres: fast and reference, forward alone (tracking
  queries) and forward+backward with the point gradient (mapping with keyframe poses optimised);
- the two decoders' forward pass without gradient (tracking, meshing) on as many points: the C++ kernel
  and the torch modules.

Points are like real rays (a camera inside the block, random pixels, 32 stratified samples between near
and far plus 11 around the surface, sorted along each ray) and, for comparison, uniform in the block.
Times are medians over repeats after a warm-up, with torch using all of the machine's cores (or
``--threads``). The machine may be shared: the load average is printed with the results. When other jobs
keep the cores busy, multi-threaded timings are dominated by threads waiting at barriers for a preempted
partner (torch's ops far more than the single-region fast kernels); ``--threads 1`` then gives the fairer
comparison.

Example::

    .venv/bin/python benchmarks/encoding.py                 # full run (a few minutes, mostly the reference)
    .venv/bin/python benchmarks/encoding.py --quick --json encoding.json

``--against COMMIT`` compares this tree's fast paths with those of another commit in one run: it exports
that commit's ``src/neb_slam_core`` (``git archive``, no worktree), builds its kernels (its install build,
or its first-use build into a private cache), and starts two worker processes of this script, one per
tree, with the same threads. The parent then times the fast measurements (hash grid forward and both
backwards, the blended forward with its Jacobian over 3 blocks, one-blob forward and forward+backward,
the decoders without gradient and with tangents, on the 44,032 ray points) in interleaved rounds, old and
new alternating first, and prints each side's median and min and the ratios new / old::

    .venv/bin/python benchmarks/encoding.py --against cd46de2 --rounds 8

Every run ends with ``record`` (``benchmarks/common.py``): ``benchmarks/results/encoding-<date>.json``, or
``encoding-against-<date>.json`` (the new side's figures under the usual keys, ``old_<key>`` and
``ratio_<key>``, and every measurement under "measurements"), and the same to ``--json FILE`` when given.

``--json FILE`` writes, for the 44,032 ray points: fast_fwd_ms, fast_fwd_bwd_ms (table grad),
fast_fwd_bwd_points_ms (point grad), reference_fwd_bwd_ms, floor_gather_ms (random rows),
floor_gather_local_ms, ratio_reference_over_fast, ratio_fast_fwd_over_floor, block_mb_t15 /
block_mb_t14 (parameter MB, 10^6 bytes, per block), one_blob_fast_fwd_ms, one_blob_fast_fwd_bwd_ms,
one_blob_reference_fwd_ms, one_blob_reference_fwd_bwd_ms, one_blob_ratio_fwd_bwd (reference over fast),
decoder_fast_fwd_ms, decoder_reference_fwd_ms, decoder_ratio_fwd,
plus the same timings per case under "cases".
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from common import REPO, commit_id, record
from tqdm import tqdm

from neb_slam_core.config import DecoderConfig, HashGridConfig, OneBlobConfig
from neb_slam_core.scene.decoders import Decoders
from neb_slam_core.scene.hash_grid import (
    HashGrid,
    HashGridMeta,
    encode_blended,
    fast_path_unavailable_reason,
    level_cells,
)
from neb_slam_core.scene.one_blob import OneBlob

N_SAMPLES_PER_RAY = 43  # 32 uniform + 11 near the surface (the paper's TUM/Replica setting)

FAST_FWD = "fast forward"
FAST_MAPPING = "fast fwd+bwd (table grad, mapping)"
FAST_TRACKING = "fast fwd+bwd (point grad, tracking)"
REFERENCE = "reference fwd+bwd (table grad)"
FLOOR_RANDOM = "floor: index_select, random rows"
FLOOR_LOCAL = "floor: index_select, encoding's rows"
BLOB_FAST_FWD = "one-blob fast forward"
BLOB_FAST_FWD_BWD = "one-blob fast fwd+bwd (point grad)"
BLOB_REF_FWD = "one-blob reference forward"
BLOB_REF_FWD_BWD = "one-blob reference fwd+bwd (point grad)"
DECODER_FAST = "decoders fast forward (no grad)"
DECODER_REF = "decoders reference forward (no grad)"
BLENDED_JACOBIAN = "fast blended forward + Jacobian (3 blocks)"
DECODER_TANGENTS = "decoders fast forward with tangents"
#: the measurements of --against: the fast paths (the kernels and their binding), in timing order
AGAINST = (
    FAST_FWD,
    FAST_MAPPING,
    FAST_TRACKING,
    BLENDED_JACOBIAN,
    BLOB_FAST_FWD,
    BLOB_FAST_FWD_BWD,
    DECODER_FAST,
    DECODER_TANGENTS,
)
#: the --json file's timing keys (median ms of the 44,032 ray points) and the measurements they hold
JSON_TIMINGS = {
    "fast_fwd_ms": FAST_FWD,
    "fast_fwd_bwd_ms": FAST_MAPPING,
    "fast_fwd_bwd_points_ms": FAST_TRACKING,
    "reference_fwd_bwd_ms": REFERENCE,
    "floor_gather_ms": FLOOR_RANDOM,
    "floor_gather_local_ms": FLOOR_LOCAL,
    "one_blob_fast_fwd_ms": BLOB_FAST_FWD,
    "one_blob_fast_fwd_bwd_ms": BLOB_FAST_FWD_BWD,
    "one_blob_reference_fwd_ms": BLOB_REF_FWD,
    "one_blob_reference_fwd_bwd_ms": BLOB_REF_FWD_BWD,
    "decoder_fast_fwd_ms": DECODER_FAST,
    "decoder_reference_fwd_ms": DECODER_REF,
}


def ray_points(n_rays: int, seed: int, edge_m: float = 5.0) -> torch.Tensor:
    """Block-local points ``(n_rays * 43, 3)`` in [0, 1]^3 sampled along rays of one camera inside the block.

    The camera sits within 0.5 m of the block centre with a random orientation and a TUM-like pinhole
    (640 x 480, f = 525 px); each ray goes through a random pixel to a surface 0.5-1.9 m away; samples are
    32 stratified between 0.1 and 2.0 m plus 11 within 5 cm of the surface, sorted along the ray, so every
    point lies inside the 5 m block.
    """
    gen = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    R_world_cam = q * torch.sign(torch.diagonal(r))  # a random rotation (up to reflection; irrelevant here)
    t_world_cam = (torch.rand(3, generator=gen, dtype=torch.float64) - 0.5) * 1.0  # block centre at 0
    u = torch.rand(n_rays, generator=gen, dtype=torch.float64) * 640
    v = torch.rand(n_rays, generator=gen, dtype=torch.float64) * 480
    d_cam = torch.stack([(u - 320) / 525, (v - 240) / 525, torch.ones_like(u)], dim=1)
    d_world = torch.nn.functional.normalize(d_cam, dim=1) @ R_world_cam.T  # (n_rays, 3)
    depth = 0.5 + 1.4 * torch.rand(n_rays, 1, generator=gen, dtype=torch.float64)
    near, far = 0.1, 2.0
    strata = (torch.arange(32, dtype=torch.float64) + torch.rand(n_rays, 32, generator=gen, dtype=torch.float64)) / 32
    t_uniform = near + (far - near) * strata
    t_surface = depth + 0.05 * (2 * torch.rand(n_rays, 11, generator=gen, dtype=torch.float64) - 1)
    t = torch.sort(torch.cat([t_uniform, t_surface], dim=1), dim=1).values  # (n_rays, 43)
    p_world = t_world_cam + t[..., None] * d_world[:, None, :]  # (n_rays, 43, 3)
    x01 = p_world / edge_m + 0.5
    assert bool(((x01 >= 0) & (x01 <= 1)).all()), "benchmark rays must stay inside the block"
    return x01.reshape(-1, 3).to(torch.float32).contiguous()


def uniform_points(n: int, seed: int) -> torch.Tensor:
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed))


def median_ms(fn, repeats: int, warmup: int = 2) -> tuple[float, float]:
    """(median, min) wall time of ``fn()`` in milliseconds."""
    for _ in range(warmup):
        fn()
    times = [time_ms(fn) for _ in range(repeats)]
    return statistics.median(times), min(times)


def time_ms(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


@dataclass
class CaseResult:
    label: str
    n_points: int
    timings: dict[str, tuple[float, float]]  # name -> (median ms, min ms)


def grid_fns(x01: torch.Tensor, cfg: HashGridConfig, with_reference: bool) -> dict:
    """The hash grid's measurements on block-local points ``x01``: name -> a call to time."""
    n = x01.shape[0]
    fast = HashGrid(cfg, backend="fast", seed=0)
    ref = HashGrid(cfg, backend="reference", seed=0)
    grad_out = torch.randn(n, fast.n_output_dims, generator=torch.Generator().manual_seed(1))

    def fast_fwd():
        with torch.no_grad():
            fast(x01)

    def fast_fwd_bwd_table():  # mapping: table gradient, fixed points
        fast.table.grad = None
        fast(x01).backward(grad_out)

    x_req = x01.clone().requires_grad_(True)

    def fast_fwd_bwd_points():  # tracking: point gradient, frozen table
        x_req.grad = None
        fast.table.requires_grad_(False)
        try:
            fast(x_req).backward(grad_out)
        finally:
            fast.table.requires_grad_(True)

    def ref_fwd_bwd_table():
        ref.table.grad = None
        ref(x01).backward(grad_out)

    fns = {FAST_FWD: fast_fwd, FAST_MAPPING: fast_fwd_bwd_table, FAST_TRACKING: fast_fwd_bwd_points}
    if with_reference:
        fns[REFERENCE] = ref_fwd_bwd_table
    return fns


def floor_fns(x01: torch.Tensor, cfg: HashGridConfig) -> dict:
    """The memory-bound floor: a bare gather of as many rows as the encoding reads."""
    grid = HashGrid(cfg, backend="reference", seed=0)
    meta, table = grid.meta, grid.table.detach()
    n_rows = x01.shape[0] * meta.n_levels * 8
    rand_rows = torch.randint(0, meta.n_entries, (n_rows,), generator=torch.Generator().manual_seed(2))
    local_rows = torch.cat([level_cells(x01, meta, level)[0].reshape(-1) for level in range(meta.n_levels)])
    assert local_rows.numel() == n_rows
    return {
        FLOOR_RANDOM: lambda: table.index_select(0, rand_rows),
        FLOOR_LOCAL: lambda: table.index_select(0, local_rows),
    }


def blended_fns(x01: torch.Tensor, cfg: HashGridConfig) -> dict:
    """Features and their Jacobian blended over 3 overlapping 5 m blocks (tracking's spatial gradients)."""
    points = (x01 - 0.5) * 5.0  # metres, around the first block's centre
    centres = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 1.0]])
    grids = [HashGrid(cfg, backend="fast", seed=s) for s in range(3)]

    def forward_jacobian():
        with torch.no_grad():
            assert encode_blended(points, centres, grids, 5.0, 0.5, jacobian=True) is not None

    return {BLENDED_JACOBIAN: forward_jacobian}


def run_case(
    label: str, x01: torch.Tensor, cfg: HashGridConfig, repeats: int, ref_repeats: int, with_reference: bool
) -> CaseResult:
    timings: dict[str, tuple[float, float]] = {}
    for name, fn in grid_fns(x01, cfg, with_reference).items():
        timings[name] = median_ms(fn, ref_repeats, warmup=1) if name == REFERENCE else median_ms(fn, repeats)
    for fns in (
        floor_fns(x01, cfg),
        one_blob_fns((x01 - 0.5) * 5.0),  # the same points in metres, block at 0
        decoder_fns(x01.shape[0]),
    ):
        timings.update({name: median_ms(fn, repeats) for name, fn in fns.items()})
    return CaseResult(label, x01.shape[0], timings)


def decoder_fns(n: int, with_tangents: bool = False) -> dict:
    """Both decoders' forward without gradient on ``n`` points (48 one-blob + 32 grid inputs), fast and
    reference, with the same weights; with ``with_tangents`` also the fast forward with 3 tangents."""
    g = torch.Generator().manual_seed(4)
    blob, feats = torch.rand(n, 48, generator=g), torch.randn(n, 32, generator=g)
    slopes, d_feats = torch.randn(n, 3, 16, generator=g), torch.randn(n, 3, 32, generator=g)
    torch.manual_seed(0)
    fast = Decoders(48, 32, DecoderConfig(), backend="fast")
    ref = Decoders(48, 32, DecoderConfig(), backend="reference")
    ref.load_state_dict(fast.state_dict())
    fns = {}
    for name, dec in ((DECODER_FAST, fast), (DECODER_REF, ref)):

        def forward(dec=dec):
            with torch.no_grad():
                dec(blob, feats)

        fns[name] = forward
    if with_tangents:
        fns[DECODER_TANGENTS] = lambda: fast.forward_with_tangents(blob, feats, slopes, d_feats)
    return fns


def one_blob_fns(points_world: torch.Tensor) -> dict:
    """The one-blob encoding's forward and forward+backward (point gradient), fast and reference."""
    n_dims = 3 * OneBlobConfig().n_bins
    grad_out = torch.randn(points_world.shape[0], n_dims, generator=torch.Generator().manual_seed(3))
    p = points_world.clone().requires_grad_(True)
    fns = {}
    for backend, (fwd_name, bwd_name) in (
        ("fast", (BLOB_FAST_FWD, BLOB_FAST_FWD_BWD)),
        ("reference", (BLOB_REF_FWD, BLOB_REF_FWD_BWD)),
    ):
        enc = OneBlob(OneBlobConfig(), backend=backend)

        def forward(enc=enc):
            with torch.no_grad():
                enc(points_world)

        def forward_backward(enc=enc):
            p.grad = None
            enc(p).backward(grad_out)

        fns[fwd_name], fns[bwd_name] = forward, forward_backward
    return fns


# ---------------------------------------------------------------------------------------------- --against


def worker(threads: int) -> int:
    """``--worker``: the fast measurements of the tree this process imports, timed on request. Reads JSON
    lines from stdin (``{"name": ..., "repeats": k}``; an empty line ends), answers each with the list of
    times in ms on the original stdout; everything else the process prints goes to stderr."""
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    torch.set_num_threads(threads)
    reason = fast_path_unavailable_reason()  # the first-use build of an old tree happens here
    if reason is not None:
        answers.write(json.dumps({"error": reason}) + "\n")
        answers.flush()
        return 1
    import neb_slam_core
    from neb_slam_core.scene import _ext

    x01 = ray_points(1024, seed=1024)
    cfg = HashGridConfig()
    fns = {
        **grid_fns(x01, cfg, with_reference=False),
        **blended_fns(x01, cfg),
        **one_blob_fns((x01 - 0.5) * 5.0),
        **decoder_fns(x01.shape[0], with_tangents=True),
    }
    fns = {name: fns[name] for name in AGAINST}
    for fn in fns.values():  # warm-up
        fn()
        fn()
    kernels = getattr(_ext, "_module", None)
    answers.write(
        json.dumps(
            {
                "package": neb_slam_core.__file__,
                "kernels": getattr(kernels, "__file__", "?"),
                "threads": torch.get_num_threads(),
                "n_points": x01.shape[0],
            }
        )
        + "\n"
    )
    answers.flush()
    for line in sys.stdin:
        if not line.strip():
            break
        request = json.loads(line)
        fn = fns[request["name"]]
        answers.write(json.dumps([time_ms(fn) for _ in range(request["repeats"])]) + "\n")
        answers.flush()
    return 0


class Worker:
    """A ``--worker`` process running the package under ``package_root``."""

    def __init__(self, label: str, package_root: Path, threads: int, env: dict | None = None):
        self.label = label
        environ = {**os.environ, **(env or {}), "PYTHONPATH": str(package_root)}
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--worker", "--threads", str(threads)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=environ,
        )
        self.info = self._read()
        if "error" in self.info:
            raise RuntimeError(f"{label}: the fast path is unavailable: {self.info['error']}")

    def _read(self):
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the {self.label} worker exited (code {self.proc.wait()})")
        return json.loads(line)

    def time(self, name: str, repeats: int) -> list[float]:
        self.proc.stdin.write(json.dumps({"name": name, "repeats": repeats}) + "\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("\n")
                self.proc.stdin.flush()
                self.proc.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()


def export_tree(commit: str, dest: Path) -> str:
    """``src/neb_slam_core`` of ``commit`` into ``dest`` (``git archive``), with its install build of the
    kernels when its setup.py has one; returns the full commit id."""

    def git(*args: str, **kwargs) -> subprocess.CompletedProcess:
        return subprocess.run(["git", "-C", str(REPO), *args], check=True, capture_output=True, **kwargs)

    full = git("rev-parse", "--verify", f"{commit}^{{commit}}", text=True).stdout.strip()
    archive = git("archive", "--format=tar", full, "src/neb_slam_core").stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(dest, filter="data")
    package = dest / "src" / "neb_slam_core"
    print(f"building the kernels of {full[:12]} in {package}", file=sys.stderr)
    subprocess.run(
        [sys.executable, "setup.py", "-q", "build_ext", "--inplace"], cwd=package, check=True, stdout=subprocess.DEVNULL
    )
    return full


def against(commit: str, threads: int, rounds: int, repeats: int, json_path: Path | None) -> int:
    """Time this tree's fast paths against ``commit``'s, interleaved in one run (see the module's doc)."""
    base = Path(tempfile.mkdtemp(prefix="enc_base_"))
    workers: list[Worker] = []
    try:
        full = export_tree(commit, base)
        # the old tree's first-use build goes to a cache of its own, made from the exported sources
        old = Worker("old", base / "src" / "neb_slam_core", threads, {"NEB_SLAM_EXT_DIR": str(base / "ext")})
        workers.append(old)
        new = Worker("new", REPO / "src" / "neb_slam_core", threads)
        workers.append(new)
        for w in workers:
            print(f"{w.label}: package {w.info['package']}, kernels {w.info['kernels']}")
        assert Path(old.info["package"]).is_relative_to(base), "the old worker imported another tree"
        assert Path(new.info["package"]).is_relative_to(REPO), "the new worker imported another tree"
        times: dict[str, dict[str, list[float]]] = {w.label: {name: [] for name in AGAINST} for w in workers}
        for r in tqdm(range(rounds), desc="interleaved rounds", unit="round"):
            for name in AGAINST:
                for w in workers if r % 2 == 0 else workers[::-1]:  # who goes first alternates
                    times[w.label][name] += w.time(name, repeats)
    finally:
        for w in workers:
            w.close()
        shutil.rmtree(base, ignore_errors=True)

    measurements = {}
    print(
        f"\nthis tree ({commit_id()}) against {full[:12]}: {new.info['n_points']:,} ray points, torch threads "
        f"{threads}, {rounds} rounds x {repeats} repeats each, load average (1 min) at the end: "
        f"{os.getloadavg()[0]:.2f}"
    )
    print(
        f"  {'':44s} {'old median':>10s} {'new median':>10s} {'new/old':>8s} {'old min':>8s} {'new min':>8s} "
        f"{'new/old':>8s}"
    )
    for name in AGAINST:
        o, n = times["old"][name], times["new"][name]
        m = {
            "old_median_ms": statistics.median(o),
            "new_median_ms": statistics.median(n),
            "old_min_ms": min(o),
            "new_min_ms": min(n),
        }
        m["ratio_median"] = m["new_median_ms"] / m["old_median_ms"]
        m["ratio_min"] = m["new_min_ms"] / m["old_min_ms"]
        measurements[name] = m
        print(
            f"  {name:44s} {m['old_median_ms']:10.2f} {m['new_median_ms']:10.2f} {m['ratio_median']:8.3f} "
            f"{m['old_min_ms']:8.2f} {m['new_min_ms']:8.2f} {m['ratio_min']:8.3f}"
        )
    figures = {
        "against": full,
        "n_points": new.info["n_points"],
        "threads": threads,
        "rounds": rounds,
        "repeats_per_round": repeats,
        "load_average_1min": os.getloadavg()[0],
    }
    for key, name in JSON_TIMINGS.items():
        if name in measurements:
            figures[key] = measurements[name]["new_median_ms"]
            figures[f"old_{key}"] = measurements[name]["old_median_ms"]
            figures[f"ratio_{key}"] = measurements[name]["ratio_median"]
    figures["measurements"] = measurements
    record("encoding-against", figures, json_path)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats, 44,032 points only")
    parser.add_argument("--json", type=Path, help="write the headline figures to this JSON file too")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch threads (default: cores)")
    parser.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="timed repeats per measurement (--against: per measurement and round, default 3)",
    )
    parser.add_argument(
        "--against", metavar="COMMIT", help="time this tree's fast paths against COMMIT's, interleaved in one run"
    )
    parser.add_argument(
        "--rounds", type=int, default=None, help="--against: interleaved rounds (default 10, --quick 4)"
    )
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)  # one side of --against
    args = parser.parse_args(argv)

    if args.worker:
        return worker(args.threads)
    if args.against:
        return against(
            args.against, args.threads, args.rounds or (4 if args.quick else 10), args.repeats or 3, args.json
        )

    torch.set_num_threads(args.threads)
    reason = fast_path_unavailable_reason()  # loads (or builds) the kernels now, outside the timings
    if reason is not None:
        print(f"the fast path is unavailable: {reason}")
        return 1

    cfg = HashGridConfig()
    block_mb_t15 = HashGrid(cfg, backend="reference").param_bytes / 1e6
    block_mb_t14 = HashGrid(HashGridConfig(log2_hashmap_size=14), backend="reference").param_bytes / 1e6
    repeats = args.repeats or (5 if args.quick else 15)
    ref_repeats = 2 if args.quick else 5

    cases = (
        [("rays", 1024), ("uniform", 1024)]
        if args.quick
        else [("rays", 1024), ("uniform", 1024), ("rays", 2560), ("uniform", 2560)]
    )
    results: list[CaseResult] = []
    for kind, n_rays in tqdm(cases, desc="benchmark cases", unit="case"):
        n = n_rays * N_SAMPLES_PER_RAY
        x01 = ray_points(n_rays, seed=n_rays) if kind == "rays" else uniform_points(n, seed=n_rays)
        with_reference = not (args.quick and kind == "uniform")
        results.append(run_case(f"{n:,} {kind}", x01, cfg, repeats, ref_repeats, with_reference))

    meta = HashGridMeta.from_config(cfg)
    print()
    print(
        f"hash-grid encoding: {meta.n_levels} levels x {meta.n_features} features, T = 2^{cfg.log2_hashmap_size}, "
        f"R {meta.level_resolutions[0]}..{meta.level_resolutions[-1]}, {meta.n_entries:,} rows"
    )
    print(f"parameters per block: {block_mb_t15:.2f} MB at T = 2^15, {block_mb_t14:.2f} MB at T = 2^14")
    print(
        f"torch threads: {torch.get_num_threads()}, load average (1 min) at the end: {os.getloadavg()[0]:.2f}, "
        f"repeats: {repeats} (reference {ref_repeats})"
    )
    for res in results:
        t = {k: v[0] for k, v in res.timings.items()}
        print(f"\n{res.label} points ({res.n_points * meta.n_levels * 8 / 1e6:.1f} M row lookups)")
        print(f"  {'':42s} {'median ms':>10s} {'min ms':>9s}")
        for name, (med, mn) in res.timings.items():
            print(f"  {name:42s} {med:10.2f} {mn:9.2f}")
        fwd = t[FAST_FWD]
        ratios = []
        if REFERENCE in t:
            ratios.append(f"reference/fast fwd+bwd = {t[REFERENCE] / t[FAST_MAPPING]:.1f}x")
        ratios.append(f"fast fwd/floor = {fwd / t[FLOOR_RANDOM]:.2f} (vs encoding's rows {fwd / t[FLOOR_LOCAL]:.2f})")
        ratios.append(f"one-blob reference/fast fwd+bwd = {t[BLOB_REF_FWD_BWD] / t[BLOB_FAST_FWD_BWD]:.1f}x")
        ratios.append(f"decoders reference/fast = {t[DECODER_REF] / t[DECODER_FAST]:.1f}x")
        print("  " + ", ".join(ratios))

    head = next(r for r in results if r.label.startswith("44,032 rays")).timings
    summary = {
        "n_points": 1024 * N_SAMPLES_PER_RAY,
        "threads": torch.get_num_threads(),
        **{key: head[name][0] for key, name in JSON_TIMINGS.items()},
        "block_mb_t15": block_mb_t15,
        "block_mb_t14": block_mb_t14,
        "load_average_1min": os.getloadavg()[0],
        "cases": {r.label: {k: {"median_ms": v[0], "min_ms": v[1]} for k, v in r.timings.items()} for r in results},
    }
    summary["ratio_reference_over_fast"] = summary["reference_fwd_bwd_ms"] / summary["fast_fwd_bwd_ms"]
    summary["ratio_fast_fwd_over_floor"] = summary["fast_fwd_ms"] / summary["floor_gather_ms"]
    summary["one_blob_ratio_fwd_bwd"] = summary["one_blob_reference_fwd_bwd_ms"] / summary["one_blob_fast_fwd_bwd_ms"]
    summary["decoder_ratio_fwd"] = summary["decoder_reference_fwd_ms"] / summary["decoder_fast_fwd_ms"]
    record("encoding", summary, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
