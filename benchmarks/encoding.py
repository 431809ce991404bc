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
import json
import math
import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from neb_slam_core.config import DecoderConfig, HashGridConfig, OneBlobConfig
from neb_slam_core.scene.decoders import Decoders
from neb_slam_core.scene.hash_grid import HashGrid, HashGridMeta, fast_path_unavailable_reason, level_cells
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
#: the --json file's timing keys (median ms of the 44,032 ray points) and the measurements they hold
JSON_TIMINGS = {
    "fast_fwd_ms": FAST_FWD, "fast_fwd_bwd_ms": FAST_MAPPING, "fast_fwd_bwd_points_ms": FAST_TRACKING,
    "reference_fwd_bwd_ms": REFERENCE, "floor_gather_ms": FLOOR_RANDOM, "floor_gather_local_ms": FLOOR_LOCAL,
    "one_blob_fast_fwd_ms": BLOB_FAST_FWD, "one_blob_fast_fwd_bwd_ms": BLOB_FAST_FWD_BWD,
    "one_blob_reference_fwd_ms": BLOB_REF_FWD, "one_blob_reference_fwd_bwd_ms": BLOB_REF_FWD_BWD,
    "decoder_fast_fwd_ms": DECODER_FAST, "decoder_reference_fwd_ms": DECODER_REF,
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
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), min(times)


@dataclass
class CaseResult:
    label: str
    n_points: int
    timings: dict[str, tuple[float, float]]  # name -> (median ms, min ms)


def run_case(label: str, x01: torch.Tensor, cfg: HashGridConfig, repeats: int, ref_repeats: int,
             with_reference: bool) -> CaseResult:
    n = x01.shape[0]
    fast = HashGrid(cfg, backend="fast", seed=0)
    ref = HashGrid(cfg, backend="reference", seed=0)
    meta: HashGridMeta = fast.meta
    grad_out = torch.randn(n, fast.n_output_dims, generator=torch.Generator().manual_seed(1))
    timings: dict[str, tuple[float, float]] = {}

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

    n_rows = n * meta.n_levels * 8
    table = fast.table.detach()
    rand_rows = torch.randint(0, meta.n_entries, (n_rows,), generator=torch.Generator().manual_seed(2))
    local_rows = torch.cat([level_cells(x01, meta, level)[0].reshape(-1) for level in range(meta.n_levels)])
    assert local_rows.numel() == n_rows

    timings[FAST_FWD] = median_ms(fast_fwd, repeats)
    timings[FAST_MAPPING] = median_ms(fast_fwd_bwd_table, repeats)
    timings[FAST_TRACKING] = median_ms(fast_fwd_bwd_points, repeats)
    if with_reference:
        timings[REFERENCE] = median_ms(ref_fwd_bwd_table, ref_repeats, warmup=1)
    timings[FLOOR_RANDOM] = median_ms(lambda: table.index_select(0, rand_rows), repeats)
    timings[FLOOR_LOCAL] = median_ms(lambda: table.index_select(0, local_rows), repeats)
    timings.update(one_blob_timings((x01 - 0.5) * 5.0, repeats))  # the same points in metres, block at 0
    timings.update(decoder_timings(n, repeats))
    return CaseResult(label, n, timings)


def decoder_timings(n: int, repeats: int) -> dict[str, tuple[float, float]]:
    """Both decoders' forward without gradient on ``n`` points (48 one-blob + 32 grid inputs), fast and
    reference, with the same weights."""
    g = torch.Generator().manual_seed(4)
    blob, feats = torch.rand(n, 48, generator=g), torch.randn(n, 32, generator=g)
    torch.manual_seed(0)
    fast = Decoders(48, 32, DecoderConfig(), backend="fast")
    ref = Decoders(48, 32, DecoderConfig(), backend="reference")
    ref.load_state_dict(fast.state_dict())
    out = {}
    for name, dec in ((DECODER_FAST, fast), (DECODER_REF, ref)):
        def forward(dec=dec):
            with torch.no_grad():
                dec(blob, feats)
        out[name] = median_ms(forward, repeats)
    return out


def one_blob_timings(points_world: torch.Tensor, repeats: int) -> dict[str, tuple[float, float]]:
    """The one-blob encoding's forward and forward+backward (point gradient), fast and reference."""
    n_dims = 3 * OneBlobConfig().n_bins
    grad_out = torch.randn(points_world.shape[0], n_dims, generator=torch.Generator().manual_seed(3))
    p = points_world.clone().requires_grad_(True)
    out = {}
    for backend, (fwd_name, bwd_name) in (("fast", (BLOB_FAST_FWD, BLOB_FAST_FWD_BWD)),
                                          ("reference", (BLOB_REF_FWD, BLOB_REF_FWD_BWD))):
        enc = OneBlob(OneBlobConfig(), backend=backend)

        def forward():
            with torch.no_grad():
                enc(points_world)

        def forward_backward():
            p.grad = None
            enc(p).backward(grad_out)

        out[fwd_name] = median_ms(forward, repeats)
        out[bwd_name] = median_ms(forward_backward, repeats)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats, 44,032 points only")
    parser.add_argument("--json", type=Path, help="write the headline figures to this JSON file")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch threads (default: cores)")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats per measurement")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    reason = fast_path_unavailable_reason()  # builds the extension now, outside the timings
    if reason is not None:
        print(f"the fast path is unavailable: {reason}")
        return 1

    cfg = HashGridConfig()
    block_mb_t15 = HashGrid(cfg, backend="reference").param_bytes / 1e6
    block_mb_t14 = HashGrid(HashGridConfig(log2_hashmap_size=14), backend="reference").param_bytes / 1e6
    repeats = args.repeats or (5 if args.quick else 15)
    ref_repeats = 2 if args.quick else 5

    cases = [("rays", 1024), ("uniform", 1024)] if args.quick else [
        ("rays", 1024), ("uniform", 1024), ("rays", 2560), ("uniform", 2560)]
    results: list[CaseResult] = []
    for kind, n_rays in tqdm(cases, desc="benchmark cases", unit="case"):
        n = n_rays * N_SAMPLES_PER_RAY
        x01 = ray_points(n_rays, seed=n_rays) if kind == "rays" else uniform_points(n, seed=n_rays)
        with_reference = not (args.quick and kind == "uniform")
        results.append(run_case(f"{n:,} {kind}", x01, cfg, repeats, ref_repeats, with_reference))

    meta = HashGridMeta.from_config(cfg)
    print()
    print(f"hash-grid encoding: {meta.n_levels} levels x {meta.n_features} features, T = 2^{cfg.log2_hashmap_size}, "
          f"R {meta.level_resolutions[0]}..{meta.level_resolutions[-1]}, {meta.n_entries:,} rows")
    print(f"parameters per block: {block_mb_t15:.2f} MB at T = 2^15, {block_mb_t14:.2f} MB at T = 2^14")
    print(f"torch threads: {torch.get_num_threads()}, load average (1 min) at the end: {os.getloadavg()[0]:.2f}, "
          f"repeats: {repeats} (reference {ref_repeats})")
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
        ratios.append(f"fast fwd/floor = {fwd / t[FLOOR_RANDOM]:.2f} "
                      f"(vs encoding's rows {fwd / t[FLOOR_LOCAL]:.2f})")
        ratios.append(f"one-blob reference/fast fwd+bwd = {t[BLOB_REF_FWD_BWD] / t[BLOB_FAST_FWD_BWD]:.1f}x")
        ratios.append(f"decoders reference/fast = {t[DECODER_REF] / t[DECODER_FAST]:.1f}x")
        print("  " + ", ".join(ratios))

    if args.json:
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
        args.json.write_text(json.dumps(summary, indent=2) + "\n")
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
