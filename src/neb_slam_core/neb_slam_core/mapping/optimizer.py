"""An optimiser over a block map that grows: one Adam parameter group per block plus the decoders.

Adding a block adds a parameter group and leaves the state (moments, step counts) of every existing
group untouched, so allocation never resets what the optimiser learned about older blocks.
"""

from __future__ import annotations

import torch

from ..scene.block_map import BlockMap


class MapOptimizer:
    """Adam over the decoders and every block's hash table, kept in step with ``block_map``.

    Args:
        block_map: the map; call :meth:`sync` (or any step) after adding blocks.
        grid_lr: learning rate of the hash tables (paper 1e-2).
        decoder_lr: learning rate of the decoders (paper 1e-2).
    """

    def __init__(
        self,
        block_map: BlockMap,
        grid_lr: float = 1e-2,
        decoder_lr: float = 1e-2,
        betas: tuple[float, float] = (0.9, 0.99),
        eps: float = 1e-15,
    ):
        self.block_map = block_map
        self.grid_lr = grid_lr
        # fused: torch's one-pass Adam kernel, the same update as the default implementation's several
        # element-wise passes over every table, in one pass; the tables are the bulk of the map's parameters
        self.optimizer = torch.optim.Adam(
            [{"params": list(block_map.decoders.parameters()), "lr": decoder_lr, "name": "decoders"}],
            betas=betas,
            eps=eps,
            fused=True,
        )
        self._n_blocks = 0
        self.sync()

    def sync(self) -> int:
        """Add a parameter group for every block allocated since the last call; returns how many."""
        added = 0
        for block in list(self.block_map.blocks)[self._n_blocks :]:
            self.optimizer.add_param_group(
                {"params": [block.grid.table], "lr": self.grid_lr, "name": f"block{block.block_id}"}
            )
            added += 1
        self._n_blocks = len(self.block_map.blocks)
        return added

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def step(self) -> None:
        self.sync()
        self.optimizer.step()

    def group(self, name: str) -> dict:
        for g in self.optimizer.param_groups:
            if g.get("name") == name:
                return g
        raise KeyError(name)
