"""Save and load a whole block map (blocks, decoders, configs, format version) to one file."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import torch

from .. import __version__
from ..config import BlockConfig, DecoderConfig, OneBlobConfig, config_from_dict, config_to_dict
from ..errors import DatasetError
from .block_map import BlockMap

MAP_FORMAT = "neb_slam_map"
MAP_FORMAT_VERSION = 1


def save_map(
    block_map: BlockMap,
    path: str | Path,
    extra: dict | None = None,
    block_keyframes: Mapping[int, Sequence[int]] | None = None,
) -> Path:
    """Write the map to ``path`` (a torch file). ``extra`` is stored alongside (e.g. keyframe poses).

    Each block's entry holds ``keyframe_ids``: its keyframes in ``block_keyframes`` (block id -> keyframe
    ids, the run's :meth:`~neb_slam_core.mapping.keyframes.KeyframeStore.block_keyframes`), empty when
    not given. The field is part of format version 1; :func:`load_map` does not read it back, since
    keyframes belong to the run that saved the map. ``observed`` is the block's record of the voxels its
    keyframes saw (:class:`~.block.NeuralBlock`); a map without it (or with another voxel size) loads with
    the whole block observed. Written to a temporary file first and renamed, so an
    interrupted save never leaves a broken file.
    """
    block_keyframes = block_keyframes or {}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": MAP_FORMAT,
        "version": MAP_FORMAT_VERSION,
        "software": __version__,
        "config": {
            "block": config_to_dict(block_map.block_cfg),
            "one_blob": config_to_dict(block_map.blob_cfg),
            "decoder": config_to_dict(block_map.decoder_cfg),
        },
        "seed": block_map.seed,
        "blocks": [
            {
                "id": b.block_id,
                "centre": b.centre.detach().cpu(),
                "table": b.grid.table.detach().cpu(),
                "observed": b.observed.detach().cpu(),
                "keyframe_ids": [int(k) for k in block_keyframes.get(b.block_id, ())],
            }
            for b in block_map.blocks
        ],
        "decoders": {k: v.detach().cpu() for k, v in block_map.decoders.state_dict().items()},
        "extra": extra or {},
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)
    return path


def load_map(path: str | Path, device: str | torch.device = "cpu", grid_backend: str = "auto") -> tuple[BlockMap, dict]:
    """Read a map written by :func:`save_map`; returns the map and the stored ``extra`` (the blocks'
    ``keyframe_ids`` are not read: see :func:`save_map`)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "map file not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt files
        raise DatasetError(path, f"not a readable map file ({type(exc).__name__}: {exc})") from None
    if not isinstance(payload, dict) or payload.get("format") != MAP_FORMAT:
        raise DatasetError(path, f"not a NeB-SLAM map (expected format {MAP_FORMAT!r})")
    if payload.get("version") != MAP_FORMAT_VERSION:
        raise DatasetError(
            path,
            f"map format version {payload.get('version')} is not supported "
            f"(this software reads version {MAP_FORMAT_VERSION})",
        )
    cfg = payload["config"]
    block_map = BlockMap(
        config_from_dict(BlockConfig, cfg["block"], "block"),
        config_from_dict(OneBlobConfig, cfg["one_blob"], "one_blob"),
        config_from_dict(DecoderConfig, cfg["decoder"], "decoder"),
        grid_backend=grid_backend,
        seed=payload["seed"],
    ).to(device)
    for entry in payload["blocks"]:
        block = block_map.add_block(entry["centre"])
        if block.grid.table.shape != entry["table"].shape:
            raise DatasetError(
                path,
                f"block {entry['id']}: table shape {tuple(entry['table'].shape)} does not match "
                f"the stored config ({tuple(block.grid.table.shape)})",
            )
        with torch.no_grad():
            block.grid.table.copy_(entry["table"])
        observed = entry.get("observed")
        if observed is not None and observed.shape == block.observed.shape:
            block.observed.copy_(observed)
        else:  # a map saved without the record (or with another voxel size): all of it counts as observed
            block.observed.fill_(True)
    block_map.decoders.load_state_dict(payload["decoders"])
    return block_map, payload.get("extra", {})
