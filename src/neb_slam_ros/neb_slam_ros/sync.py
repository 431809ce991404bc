"""Pairing colour and depth images by stamp (what message_filters' approximate time policy does for two
topics; message_filters is not available as a wheel, and the rule here is small and tested).

Messages are pushed as they arrive. A pair is emitted as soon as both halves are there: same stamp, or
the nearest within ``slop_ns``. A stamp that is not newer than the last paired one (out of order, or
a duplicate) is refused with a reason, so that the engine always sees time moving forward. A pair is
stamped with its depth image's stamp, or its colour image's (``frame_stamp``, see
:data:`neb_slam_core.datasets.base.FRAME_STAMPS`).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

from neb_slam_core.datasets.base import check_frame_stamp, frame_stamps


@dataclass
class Pair:
    """A colour and a depth message that belong to one frame; ``stamp_ns`` is the frame's (``frame_stamp``)."""

    stamp_ns: int
    rgb: Any
    depth: Any


class StampPairer:
    """Pairs two streams by stamp. ``capacity`` unmatched messages are kept per stream (oldest dropped)."""

    def __init__(self, slop_ns: int, capacity: int = 30, frame_stamp: str = "depth"):
        self.slop_ns = int(slop_ns)
        self.frame_stamp = check_frame_stamp("frame_stamp", frame_stamp)
        self.capacity = capacity
        self._pending: dict[str, OrderedDict[int, Any]] = {"rgb": OrderedDict(), "depth": OrderedDict()}
        self.last_stamp_ns: int | None = None

    def push(self, stream: str, stamp_ns: int, msg: Any) -> tuple[list[Pair], str]:
        """Add ``msg`` of ``stream`` ('rgb' or 'depth'); returns the completed pairs (oldest first) and
        why the message was refused ('' when it was not)."""
        if self.last_stamp_ns is not None and stamp_ns <= self.last_stamp_ns:
            kind = "a duplicate of" if stamp_ns == self.last_stamp_ns else "older than"
            return [], f"stamp {stamp_ns} ns is {kind} the last frame's ({self.last_stamp_ns} ns)"
        own = self._pending[stream]
        if stamp_ns in own:
            return [], f"stamp {stamp_ns} ns is a duplicate of a message still waiting for its pair"
        own[stamp_ns] = msg
        while len(own) > self.capacity:
            own.popitem(last=False)
        return self._match(), ""

    def _match(self) -> list[Pair]:
        pairs = []
        rgb, depth = self._pending["rgb"], self._pending["depth"]
        while rgb and depth:
            best = None
            for s_rgb in rgb:
                s_depth = min(depth, key=lambda s: abs(s - s_rgb))
                if abs(s_depth - s_rgb) <= self.slop_ns:
                    best = (s_rgb, s_depth)
                    break
            if best is None:
                break
            s_rgb, s_depth = best
            pairs.append(Pair(frame_stamps(s_rgb, s_depth, self.frame_stamp), rgb.pop(s_rgb), depth.pop(s_depth)))
            self.last_stamp_ns = max(s_rgb, s_depth)
            # whatever is older than the pair can no longer be paired in order
            for stream in (rgb, depth):
                for s in [s for s in stream if s <= self.last_stamp_ns]:
                    del stream[s]
        return pairs
