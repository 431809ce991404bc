"""Temporarily stop gradients into the map's parameters (tracking optimises the pose only)."""

from __future__ import annotations

from contextlib import contextmanager

from torch import nn


@contextmanager
def frozen(module: nn.Module):
    """Within the block, ``module``'s parameters do not require grad (so no table gradient is computed)."""
    params = [p for p in module.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield module
    finally:
        for p in params:
            p.requires_grad_(True)
