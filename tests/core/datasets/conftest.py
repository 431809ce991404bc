"""Helpers that build tiny fake dataset folders (8x6 images) whose values the tests know exactly."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

W, H = 8, 6


class Fake:
    """Writers for images and poses; colour is given as RGB, written as the BGR files cv2 expects."""

    W, H = W, H

    @staticmethod
    def rgb(path: Path, color=(10, 100, 200), size=(W, H)) -> np.ndarray:
        """Write a uniform colour image (any cv2 extension) and return the (H, W, 3) RGB array."""
        img = np.empty((size[1], size[0], 3), np.uint8)
        img[:] = color
        Fake.rgb_array(path, img)
        return img

    @staticmethod
    def rgb_array(path: Path, img: np.ndarray) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))

    @staticmethod
    def depth(path: Path, value: int | np.ndarray = 1000, size=(W, H), dtype=np.uint16) -> np.ndarray:
        """Write a single-channel depth PNG (uniform ``value`` or a given array) and return the raw array."""
        raw = np.asarray(value, dtype=dtype)
        if raw.ndim == 0:
            raw = np.full((size[1], size[0]), value, dtype=dtype)
        path.parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(path), raw)
        return raw

    @staticmethod
    def pose(k: float) -> np.ndarray:
        """A distinct rigid pose per k: rotation by k * 30 degrees about z, translation (k, 2k, -k)."""
        a = np.deg2rad(30.0 * k)
        T = np.eye(4)
        T[:3, :3] = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = [k, 2.0 * k, -k]
        return T

    @staticmethod
    def matrix_text(T: np.ndarray) -> str:
        """A 4x4 as 4 lines of 4 numbers (repr precision, so it reads back exactly)."""
        return "\n".join(" ".join(repr(float(v)) for v in row) for row in T) + "\n"


@pytest.fixture
def fake() -> type[Fake]:
    return Fake


@pytest.fixture
def skip_warnings(caplog):
    """Returns a function giving the loader summary warnings ('skipped N of M frames') logged so far."""
    caplog.set_level(logging.WARNING)

    def records() -> list[logging.LogRecord]:
        return [r for r in caplog.records if r.levelno == logging.WARNING and "skipped" in r.getMessage()]

    return records
