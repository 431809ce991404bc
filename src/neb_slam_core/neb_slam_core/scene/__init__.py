"""The scene representation: neural blocks, their hash-grid encoding, the shared decoders, the block map."""

from .hash_grid import HashGrid, HashGridMeta, encode_reference, hash_grid_param_count

__all__ = ["HashGrid", "HashGridMeta", "encode_reference", "hash_grid_param_count"]
