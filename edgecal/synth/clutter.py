"""Backgrounds seen behind the boards: uniform, or clutter with checker-like distractors.

Clutter is drawn in image space (it only has to look busy, it carries no geometry): a smooth shading,
random plates, bars, lines and ellipses, and distractors that fool weak detectors: a 2x2 checker patch
(one real X-junction), a ladder of alternating squares, a card of separated dark tiles (a grid of
squares that do not touch), a grid of dots, stripes and text-like blobs. None forms a chessboard of 2x2
or more inner corners, so a negative stays a negative.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike

_SHIFT = 4  # cv2 drawing with 1/16 px vertex precision
_ONE = 1 << _SHIFT

DISTRACTORS = ("checker", "ladder", "tiles", "dots", "stripes", "text")


def _fx(pts: ArrayLike) -> np.ndarray:
    return np.round(np.asarray(pts, dtype=np.float64) * _ONE).astype(np.int32)


def _rotated_rect(cx: float, cy: float, w: float, h: float, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    corners = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
    return corners @ np.array([[c, s], [-s, c]]) + np.array([cx, cy])


def _poly(img: np.ndarray, pts: np.ndarray, value: int) -> None:
    cv2.fillPoly(img, [_fx(pts)], int(value), cv2.LINE_AA, _SHIFT)


def _grid_patch(img: np.ndarray, rng: np.random.Generator, cx: float, cy: float, angle: float, cell: float,
                cells: list[tuple[float, float, float, float, int]]) -> None:
    """Draw rectangles given in a local frame (x, y, w, h, value), rotated by ``angle`` about (cx, cy)."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, s], [-s, c]])
    for x, y, w, h, v in cells:
        local = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]]) * cell
        _poly(img, local @ rot + np.array([cx, cy]), v)


def _distractor(img: np.ndarray, rng: np.random.Generator, kind: str) -> None:
    h, w = img.shape
    scale = min(w, h)
    cx, cy = rng.uniform(0.1, 0.9) * w, rng.uniform(0.1, 0.9) * h
    angle = rng.uniform(0, np.pi)
    dark, light = int(rng.integers(0, 60)), int(rng.integers(190, 256))
    if kind == "checker":
        cell = rng.uniform(0.02, 0.06) * scale
        _grid_patch(img, rng, cx, cy, angle, cell, [(-1, -1, 1, 1, dark), (0, -1, 1, 1, light),
                                                    (-1, 0, 1, 1, light), (0, 0, 1, 1, dark)])
    elif kind == "ladder":
        cell = rng.uniform(0.015, 0.04) * scale
        n = int(rng.integers(4, 9))
        _grid_patch(img, rng, cx, cy, angle, cell, [(k - n / 2, -0.5, 1, 1, dark if k % 2 else light)
                                                    for k in range(n)])
    elif kind == "tiles":
        cell = rng.uniform(0.015, 0.035) * scale
        nx, ny = int(rng.integers(4, 9)), int(rng.integers(3, 7))
        cells = [(-nx * 0.75 - 0.5, -ny * 0.75 - 0.5, nx * 1.5 + 1.0, ny * 1.5 + 1.0, light)]
        cells += [(-nx * 0.75 + 1.5 * a, -ny * 0.75 + 1.5 * b, 1, 1, dark) for a in range(nx) for b in range(ny)]
        _grid_patch(img, rng, cx, cy, angle, cell, cells)
    elif kind == "dots":
        step = rng.uniform(0.02, 0.05) * scale
        nx, ny = int(rng.integers(3, 8)), int(rng.integers(3, 6))
        c, s = np.cos(angle), np.sin(angle)
        for a in range(nx):
            for b in range(ny):
                x, y = (a - nx / 2) * step, (b - ny / 2) * step
                p = (cx + c * x - s * y, cy + s * x + c * y)
                cv2.circle(img, tuple(int(v) for v in _fx(p)), int(step * 0.3 * _ONE), dark, -1, cv2.LINE_AA, _SHIFT)
    elif kind == "stripes":
        cell = rng.uniform(0.01, 0.03) * scale
        n = int(rng.integers(4, 10))
        length = rng.uniform(4, 10)
        _grid_patch(img, rng, cx, cy, angle, cell, [(2 * k - n, -length / 2, 1, length, dark) for k in range(n)])
    elif kind == "text":
        letters = "ABCDEFGHKMNPRSTUVWXYZ0123456789"
        text = "".join(letters[int(i)] for i in rng.integers(0, len(letters), int(rng.integers(3, 10))))
        font_scale = rng.uniform(0.6, 2.5) * scale / 480
        cv2.putText(img, text, (int(rng.uniform(0, 0.7) * w), int(cy)), cv2.FONT_HERSHEY_SIMPLEX, font_scale,
                    dark if rng.random() < 0.7 else light, max(1, int(font_scale * 2)), cv2.LINE_AA)
    else:
        raise ValueError(f"unknown distractor {kind!r} (one of {', '.join(DISTRACTORS)})")


def clutter_background(rng: np.random.Generator, size: tuple[int, int], n_shapes: int | None = None,
                       distractors: list[str] | None = None) -> tuple[np.ndarray, list[str]]:
    """A cluttered background (h, w) float32 albedo in [0, 1] and the distractor kinds drawn on it.

    ``distractors`` None picks 1..3 at random; [] draws none.
    """
    w, h = size
    scale = min(w, h)
    # Smooth shading: a few random values blown up with cubic interpolation.
    coarse = rng.uniform(70, 200, size=(int(rng.integers(2, 5)), int(rng.integers(2, 6)))).astype(np.float32)
    img = np.clip(cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC), 0, 255).astype(np.uint8)
    n = int(rng.integers(10, 30)) if n_shapes is None else int(n_shapes)
    for _ in range(n):
        kind = rng.random()
        v = int(rng.integers(20, 240))
        cx, cy = rng.uniform(-0.05, 1.05) * w, rng.uniform(-0.05, 1.05) * h
        if kind < 0.35:
            _poly(img, _rotated_rect(cx, cy, rng.uniform(0.03, 0.3) * scale, rng.uniform(0.03, 0.3) * scale,
                                     rng.uniform(0, np.pi)), v)
        elif kind < 0.6:
            p1 = _fx((cx, cy))
            p2 = _fx((cx + rng.normal(0, 0.4) * w, cy + rng.normal(0, 0.4) * h))
            cv2.line(img, tuple(int(t) for t in p1), tuple(int(t) for t in p2), v, int(rng.integers(1, 6)),
                     cv2.LINE_AA, _SHIFT)
        elif kind < 0.8:
            axes = (int(rng.uniform(0.02, 0.15) * scale * _ONE), int(rng.uniform(0.02, 0.15) * scale * _ONE))
            cv2.ellipse(img, tuple(int(t) for t in _fx((cx, cy))), axes, float(rng.uniform(0, 180)), 0, 360, v,
                        -1 if rng.random() < 0.6 else int(rng.integers(1, 4)), cv2.LINE_AA, _SHIFT)
        else:
            pts = _rotated_rect(cx, cy, rng.uniform(0.05, 0.3) * scale, rng.uniform(0.05, 0.3) * scale,
                                rng.uniform(0, np.pi))
            cv2.polylines(img, [_fx(pts)], True, v, int(rng.integers(1, 4)), cv2.LINE_AA, _SHIFT)
    if distractors is None:
        distractors = [DISTRACTORS[int(i)] for i in rng.integers(0, len(DISTRACTORS), int(rng.integers(1, 4)))]
    for name in distractors:
        _distractor(img, rng, name)
    return img.astype(np.float32) / 255.0, list(distractors)


def uniform_background(size: tuple[int, int], level: float = 0.5) -> np.ndarray:
    """A uniform background (h, w) float32 of albedo ``level``."""
    w, h = size
    return np.full((h, w), float(level), dtype=np.float32)
