"""How many bytes the engine's stores hold: what a long run's memory grows by.

:func:`deep_bytes` walks an object graph and adds up what it reaches: Python objects (``sys.getsizeof``),
numpy arrays (their buffers, a view's base once) and torch tensors (their storages, once each). Pympler's
``asizeof`` walks graphs the same way but sees a torch tensor's Python object only, not its storage, and
the engine's stores are mostly tensors; so the walk is written here.
"""

from __future__ import annotations

import sys
import types

import numpy as np
import torch

_SKIP = (type, types.ModuleType, types.FunctionType, types.MethodType, types.BuiltinFunctionType)


def deep_bytes(*roots: object, exclude: tuple[object, ...] = ()) -> int:
    """Bytes reachable from ``roots``, each object counted once; objects in ``exclude`` (and what only
    they reach) are not entered."""
    seen: set[int] = {id(x) for x in exclude}
    storages: set[int] = set()
    total = 0
    stack = list(roots)
    while stack:
        obj = stack.pop()
        if id(obj) in seen or isinstance(obj, _SKIP) or obj is None:
            continue
        seen.add(id(obj))
        if isinstance(obj, torch.Tensor):
            storage = obj.untyped_storage()
            if storage.data_ptr() not in storages:
                storages.add(storage.data_ptr())
                total += storage.nbytes()
            total += sys.getsizeof(obj)
            continue
        if isinstance(obj, np.ndarray):  # an owning array's size includes its buffer; a view's does not
            total += sys.getsizeof(obj)
            if obj.base is not None:
                stack.append(obj.base)
            continue
        total += sys.getsizeof(obj)
        if isinstance(obj, (str, bytes, int, float, bool, complex, np.generic)):
            continue
        if isinstance(obj, dict):
            stack.extend(obj.keys())
            stack.extend(obj.values())
        elif isinstance(obj, (list, tuple, set, frozenset)):
            stack.extend(obj)
        if hasattr(obj, "__dict__"):
            stack.append(obj.__dict__)
        if hasattr(type(obj), "__slots__"):
            stack.extend(getattr(obj, s) for s in type(obj).__slots__ if hasattr(obj, s))
    return total
