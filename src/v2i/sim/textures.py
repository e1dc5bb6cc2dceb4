"""Procedural textures of the rendered world: bodies, facades, roofs (numpy + OpenCV).

Every texture is drawn in metres on a face of known size at ``res_m`` metres per texel, from
an injected generator, so that the same seed gives the same pixels. Textures carry enough
high-frequency detail (window pillars, panel seams, plates, wheels, stickers, grime) for ORB
to find corners that survive a change of viewpoint.

Face conventions (a body's box frame: x forward, y left, z up): a face is seen from outside,
unmirrored; ``left``/``right`` side textures have the body's front at column 0 / at the last
column, ``top`` has the front at the last column and the body's left at row 0. Pedestrian,
cyclist and motorcycle textures are BGRA: alpha 0 where the box is empty (the figure's
silhouette is what the camera sees).
"""

from __future__ import annotations

import cv2
import numpy as np

FACES = ("front", "back", "left", "right", "top")
BODY_RES_M = 0.02  # actor texture resolution, m per texel
BODY_COLOURS = np.array([  # BGR
    (235, 235, 235), (28, 28, 30), (190, 190, 186), (120, 121, 122), (40, 40, 185), (150, 75, 30),
    (85, 40, 20), (60, 105, 45), (40, 195, 230), (30, 115, 225), (150, 178, 200), (40, 70, 110),
], dtype=np.uint8)
CLOTHES = np.array([(40, 40, 40), (120, 60, 30), (50, 50, 160), (200, 200, 200), (60, 120, 60), (30, 90, 170),
                    (140, 140, 140), (90, 40, 90), (20, 160, 200), (100, 100, 40)], dtype=np.uint8)
SKIN = np.array([(170, 195, 230), (120, 150, 200), (80, 110, 160), (60, 80, 110)], dtype=np.uint8)
GLASS = (62, 52, 45)
TYRE = (22, 22, 24)


def mip_levels(image: np.ndarray, min_side_px: int = 4) -> tuple[np.ndarray, ...]:
    """Image pyramid, level 0 = ``image``: each level halves the previous by area averaging
    (level-L texel i covers level-0 texels [2^L i, 2^L (i + 1)))."""
    levels = [image]
    while min(levels[-1].shape[:2]) >= 2 * min_side_px:
        h, w = levels[-1].shape[:2]
        levels.append(cv2.resize(levels[-1], (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    return tuple(levels)


def smooth_noise(rng: np.random.Generator, shape_hw: tuple[int, int], cell_px: float) -> np.ndarray:
    """Zero-mean, unit-ish std value noise (H, W) float32 with features ``cell_px`` texels apart."""
    h, w = shape_hw
    gh, gw = int(np.ceil(h / cell_px)) + 2, int(np.ceil(w / cell_px)) + 2
    grid = rng.standard_normal((gh, gw), dtype=np.float32)
    up = cv2.resize(grid, (round(gw * cell_px), round(gh * cell_px)), interpolation=cv2.INTER_CUBIC)
    return up[:h, :w]


def add_grain(image: np.ndarray, rng: np.random.Generator, sigma: float, blotch_sigma: float = 0.0,
              blotch_px: float = 8.0) -> np.ndarray:
    """Colour channels + fine Gaussian grain (sigma) + smooth blotches (blotch_sigma); alpha kept."""
    h, w = image.shape[:2]
    delta = rng.standard_normal((h, w), dtype=np.float32) * sigma
    if blotch_sigma > 0:
        delta += smooth_noise(rng, (h, w), blotch_px) * blotch_sigma
    out = image.copy()
    out[..., :3] = np.clip(image[..., :3].astype(np.float32) + delta[..., None], 0, 255).astype(np.uint8)
    return out


class Painter:
    """A texture of ``w_m`` x ``h_m`` metres drawn in metres: x right from the left edge, y up
    from the bottom edge (as the face is seen). BGR, or BGRA with a transparent background."""

    def __init__(self, w_m: float, h_m: float, res_m: float, colour, alpha: bool = False):
        self.res, self.h_m = res_m, h_m
        self.w_px, self.h_px = max(round(w_m / res_m), 4), max(round(h_m / res_m), 4)
        self.alpha = alpha
        self.img = np.zeros((self.h_px, self.w_px, 4 if alpha else 3), np.uint8)
        if colour is not None:
            self.img[:] = self._c(colour)

    def _c(self, colour) -> tuple:
        c = tuple(int(v) for v in colour)
        return c + (255,) if self.alpha and len(c) == 3 else c

    def p(self, x_m: float, y_m: float) -> tuple[int, int]:
        return round(x_m / self.res), round((self.h_m - y_m) / self.res)

    def rect(self, x0, y0, x1, y1, colour, thickness: int = -1) -> None:
        cv2.rectangle(self.img, self.p(x0, y1), self.p(x1, y0), self._c(colour), thickness)

    def poly(self, pts_m, colour) -> None:
        cv2.fillPoly(self.img, [np.array([self.p(x, y) for x, y in pts_m], np.int32)], self._c(colour), cv2.LINE_AA)

    def circle(self, x, y, r_m, colour, thickness_m: float | None = None) -> None:
        t = -1 if thickness_m is None else max(round(thickness_m / self.res), 1)
        cv2.circle(self.img, self.p(x, y), max(round(r_m / self.res), 1), self._c(colour), t, cv2.LINE_AA)

    def ellipse(self, x, y, rx_m, ry_m, colour) -> None:
        axes = (max(round(rx_m / self.res), 1), max(round(ry_m / self.res), 1))
        cv2.ellipse(self.img, self.p(x, y), axes, 0, 0, 360, self._c(colour), -1, cv2.LINE_AA)

    def line(self, x0, y0, x1, y1, colour, width_m: float) -> None:
        cv2.line(self.img, self.p(x0, y0), self.p(x1, y1), self._c(colour), max(round(width_m / self.res), 1),
                 cv2.LINE_AA)


def shade(colour, k: float) -> tuple:
    return tuple(int(np.clip(c * k, 0, 255)) for c in colour)


def marks(pt: Painter, rng: np.random.Generator, x0, y0, x1, y1, count: int, size_m: float) -> None:
    """Stickers, scratches and grime: small contrasting shapes in [x0, x1] x [y0, y1] (m)."""
    if x1 <= x0 or y1 <= y0:
        return
    for _ in range(count):
        x, y = rng.uniform(x0, x1), rng.uniform(y0, y1)
        s = size_m * rng.uniform(0.4, 1.0)
        colour = rng.integers(0, 256, 3) if rng.random() < 0.5 else (rng.integers(0, 2, 3) * 230 + 15)
        kind = rng.integers(0, 3)
        if kind == 0:
            pt.rect(x, y, x + s, y + 0.6 * s, colour)
        elif kind == 1:
            pt.circle(x, y, 0.4 * s, colour)
        else:
            pt.line(x, y, x + s * rng.uniform(-1, 1), y + s * rng.uniform(-1, 1), colour, 0.02)


def glyphs(pt: Painter, rng: np.random.Generator, x0, y0, x1, y1, colour) -> None:
    """Glyph-like vertical bars (a plate's characters, a logo's lettering) filling a box."""
    n = max(int((x1 - x0) / (0.7 * (y1 - y0))), 2)
    step = (x1 - x0) / n
    for k in range(n):
        a = x0 + k * step + 0.15 * step
        b = a + 0.7 * step
        shape = rng.integers(0, 4)
        pt.rect(a, y0, a + 0.22 * step, y1, colour)
        if shape >= 1:
            pt.rect(a, y1 - 0.2 * (y1 - y0), b, y1, colour)
        if shape >= 2:
            pt.rect(a, y0, b, y0 + 0.2 * (y1 - y0), colour)
        if shape == 3:
            pt.rect(b - 0.22 * step, y0, b, y1, colour)


def glass(pt: Painter, rng: np.random.Generator, x0, y0, x1, y1) -> None:
    """Dark glass with a couple of sky reflections (bright diagonal streaks)."""
    pt.rect(x0, y0, x1, y1, shade(GLASS, rng.uniform(0.8, 1.3)))
    for _ in range(rng.integers(1, 4)):
        x = rng.uniform(x0, x1)
        w = rng.uniform(0.05, 0.2)
        top, bottom = min(x + 0.3 * (y1 - y0), x1), max(min(x, x1 - w), x0)
        pt.poly([(bottom, y0), (min(bottom + w, x1), y0), (min(top + w, x1), y1), (top, y1)],
                shade((150, 140, 130), rng.uniform(0.6, 1.0)))


FACADE_COLOURS = np.array([(170, 190, 205), (120, 130, 150), (70, 80, 150), (200, 200, 195), (140, 140, 135),
                           (95, 120, 165), (180, 175, 160), (60, 65, 70)], dtype=np.uint8)
FACADE_RES_M = 0.08


def facade_texture(rng: np.random.Generator, length_m: float, height_m: float, style: dict) -> np.ndarray:
    """A building wall (length x height m): shop front at street level, window grid above."""
    wall = style["wall"]
    pt = Painter(length_m, height_m, FACADE_RES_M, wall)
    bay, floor = style["bay_m"], style["floor_m"]
    n_bays = max(int(length_m // bay), 1)
    x_off = (length_m - n_bays * bay) / 2
    pt.rect(0, 0, length_m, 0.5, shade(wall, 0.6))  # plinth
    for k in range(n_bays):
        x0 = x_off + k * bay
        if rng.random() < 0.2:  # a door
            pt.rect(x0 + 0.3 * bay, 0, x0 + 0.7 * bay, 2.4, (40, 45, 55))
        else:  # shop window
            glass(pt, rng, x0 + 0.15, 0.6, x0 + bay - 0.15, 3.2)
        for y in np.arange(style["ground_m"], height_m - floor + 0.5, floor):
            ww = style["window_w"]
            lit = rng.random() < 0.12
            colour = (120, 190, 230) if lit else shade(GLASS, rng.uniform(0.7, 1.6))
            a, b = x0 + (bay - ww) / 2, y + 0.9
            pt.rect(a - 0.1, b - 0.15, a + ww + 0.1, b + style["window_h"] + 0.1, shade(wall, 1.25))
            pt.rect(a, b, a + ww, b + style["window_h"], colour)
            if rng.random() < 0.4:  # blind
                pt.rect(a, b + style["window_h"] * rng.uniform(0.4, 0.9), a + ww, b + style["window_h"], (180, 185, 190))
            pt.line(a + ww / 2, b, a + ww / 2, b + style["window_h"], shade(wall, 0.9), 0.06)
    pt.rect(0, 3.5, length_m, 3.8, shade(wall, 0.7))  # cornice over the shops
    pt.rect(0, height_m - 0.6, length_m, height_m, shade(wall, 0.8))
    return add_grain(pt.img, rng, 4.0, 8.0, 30.0)


def facade_style(rng: np.random.Generator) -> dict:
    return {"wall": FACADE_COLOURS[rng.integers(len(FACADE_COLOURS))], "bay_m": rng.uniform(2.6, 3.8),
            "floor_m": rng.uniform(3.0, 3.6), "window_w": rng.uniform(1.0, 1.6), "window_h": rng.uniform(1.3, 1.8),
            "ground_m": 4.0}


def roof_texture(rng: np.random.Generator, w_m: float, h_m: float) -> np.ndarray:
    """Flat gravel roof with a few vents, ``w_m`` x ``h_m`` (m) at 0.1 m per texel."""
    pt = Painter(w_m, h_m, 0.1, (105, 108, 110))
    for _ in range(int(w_m * h_m / 150) + 1):
        x, y = rng.uniform(0, w_m), rng.uniform(0, h_m)
        pt.rect(x, y, x + rng.uniform(1, 4), y + rng.uniform(1, 3), (150, 150, 150))
    return add_grain(pt.img, rng, 6.0, 10.0, 25.0)
