"""Textures and part boxes of the rendered bodies: vehicles, pedestrians, riders.

A body is one or more boxes (``Part``) in its own frame (x forward, y left, z up from its
bottom), each with five textured faces (``v2i.sim.textures`` conventions). A car is two boxes,
a body up to the bonnet and a narrower glass cabin on it, so that it reads as a car from any
side; vans, trucks and buses are single boxes; pedestrians and riders are single boxes whose
BGRA textures are transparent around the figure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.classes import ObjectClass

from v2i.sim.textures import (
    BODY_COLOURS,
    BODY_RES_M,
    CLOTHES,
    SKIN,
    TYRE,
    Painter,
    add_grain,
    glass,
    glyphs,
    marks,
    mip_levels,
    shade,
)


@dataclass(frozen=True)
class Part:
    """A box of a body: centre offset ``dx_m`` forward, size ``lwh`` (m), bottom ``z0_m`` above
    the body's bottom, and the mip levels of its five face textures (face name -> levels)."""

    dx_m: float
    lwh: tuple[float, float, float]
    z0_m: float
    faces: dict
    billboard: bool = False  # a figure: drawn as one quad facing the viewer


# ------------------------------------------------------------------ vehicles
@dataclass(frozen=True)
class _Shape:
    """Side layout of a vehicle class, as fractions of length (from the front) and height."""

    band: tuple[float, float]  # glass band, fractions of h
    glass: tuple[float, float]  # glass extent along the length, fractions from the front
    pillars: tuple[float, ...]  # pillar positions, fractions from the front
    axles: tuple[float, ...]  # wheel centres, fractions from the front
    wheel_r_m: float
    logo: bool


SHAPES = {
    ObjectClass.VAN: _Shape((0.62, 0.86), (0.04, 0.27), (0.04, 0.27), (0.17, 0.79), 0.36, True),
    ObjectClass.TRUCK: _Shape((0.66, 0.86), (0.02, 0.19), (0.02, 0.19), (0.12, 0.7, 0.84), 0.5, True),
    ObjectClass.BUS: _Shape((0.5, 0.86), (0.02, 0.98), tuple(np.linspace(0.02, 0.98, 10)), (0.15, 0.76), 0.5, False),
    ObjectClass.UNKNOWN: _Shape((0.6, 0.85), (0.05, 0.3), (0.05, 0.3), (0.18, 0.8), 0.35, False),
}


def _wheel(pt: Painter, x, r) -> None:
    pt.circle(x, r, r * 1.12, (12, 12, 12))  # arch shadow
    pt.circle(x, r, r, TYRE)
    pt.circle(x, r, 0.6 * r, (165, 165, 165))
    for a in np.linspace(0, 2 * np.pi, 6)[:-1]:
        pt.line(x, r, x + 0.55 * r * np.cos(a), r + 0.55 * r * np.sin(a), (70, 70, 70), 0.03)
    pt.circle(x, r, 0.15 * r, (50, 50, 50))


def _vehicle_side(rng, cls, l, h, body) -> np.ndarray:
    """Left side, front at column 0 (x measured from the front)."""
    s = SHAPES.get(cls, SHAPES[ObjectClass.UNKNOWN])
    pt = Painter(l, h, BODY_RES_M, body)
    r = min(s.wheel_r_m, 0.3 * h)
    pt.rect(0, 0, l, 0.5 * r, (25, 25, 27))  # underbody gap
    pt.rect(0, 0.5 * r, l, 0.5 * r + 0.12, shade(body, 0.55))  # sill
    if cls in (ObjectClass.TRUCK, ObjectClass.VAN) and s.logo:  # cargo: own colour and a logo
        x0 = (s.glass[1] + 0.03) * l
        if cls == ObjectClass.TRUCK:
            pt.rect(x0 - 0.1, 0.5 * r, x0, h, (20, 20, 20))
            pt.rect(x0, 1.2 * r, l, h, BODY_COLOURS[rng.integers(len(BODY_COLOURS))])
        logo = tuple(int(v) for v in rng.integers(0, 256, 3))
        pt.rect(x0 + 0.3, 0.55 * h, x0 + 0.3 + 0.35 * h, 0.55 * h + 0.35 * h * 0.8, logo)
        glyphs(pt, rng, x0 + 0.45 + 0.35 * h, 0.6 * h, min(l - 0.3, x0 + 0.45 + 1.8 * h), 0.75 * h, shade(logo, 0.4))
    g0, g1 = s.band[0] * h, s.band[1] * h
    glass(pt, rng, s.glass[0] * l, g0, s.glass[1] * l, g1)
    for p in s.pillars:
        pt.rect(p * l - 0.06, g0, p * l + 0.06, g1, shade(body, 0.8))
    for p in s.pillars[:-1]:  # door seams and handles behind each pillar
        x = p * l + 0.04
        pt.line(x, 0.5 * r + 0.12, x, g0, shade(body, 0.45), 0.015)
        pt.rect(x + 0.25, g0 - 0.14, x + 0.45, g0 - 0.09, shade(body, 0.4))
    pt.rect(0.02, g0 - 0.1, 0.12, g0 - 0.02, (30, 120, 230))  # side marker
    pt.rect(0, g1, l, h, shade(body, 1.12))  # roof rail catches the sky
    for a in s.axles:
        _wheel(pt, a * l, r)
    marks(pt, rng, 0.1 * l, r, 0.9 * l, g0, int(rng.integers(2, 6)), 0.12)
    return add_grain(pt.img, rng, 3.0, 6.0, 20.0)


def _vehicle_end(rng, cls, w, h, body, front: bool, with_glass: bool = True) -> np.ndarray:
    """Front or back face (w x h) as seen from outside; lamps 0.7 m up (lower on a low face)."""
    pt = Painter(w, h, BODY_RES_M, body)
    lamp_y = min(0.7, h - 0.2)
    tall = cls in (ObjectClass.VAN, ObjectClass.TRUCK, ObjectClass.BUS)
    g0 = (0.5 if tall else 0.6) * h
    pt.rect(0, 0, w, 0.22, (25, 25, 27))
    pt.rect(0.02, 0, 0.22, 0.45, TYRE)
    pt.rect(w - 0.22, 0, w - 0.02, 0.45, TYRE)
    pt.rect(0, 0.22, w, 0.42, shade(body, 0.6))  # bumper
    if with_glass and (front or cls != ObjectClass.TRUCK):
        inset = 0.08 * w
        glass(pt, rng, inset, g0, w - inset, 0.92 * h)
    elif with_glass:  # the cargo box's doors
        pt.line(w / 2, 0.45, w / 2, h - 0.1, (30, 30, 30), 0.03)
        for x in (w / 2 - 0.15, w / 2 + 0.15):
            pt.line(x, 0.9, x, 0.9 + 0.5, (90, 90, 90), 0.04)
    lamp = (210, 235, 245) if front else (30, 30, 200)
    for x in (0.1, w - 0.42):
        pt.rect(x, lamp_y, x + 0.32, lamp_y + 0.15, lamp)
        pt.rect(x, lamp_y, x + 0.32, lamp_y + 0.15, (40, 40, 40), 1)
    if front:
        for y in np.arange(0.45, lamp_y, 0.05):  # grille slats
            pt.line(0.5, y, w - 0.5, y, (35, 35, 35), 0.025)
    pt.rect(w / 2 - 0.26, 0.28, w / 2 + 0.26, 0.39, (235, 235, 235))  # plate
    glyphs(pt, rng, w / 2 - 0.23, 0.3, w / 2 + 0.23, 0.37, (20, 20, 20))
    marks(pt, rng, 0.1, 0.45, w - 0.2, (g0 if with_glass else h) - 0.05, int(rng.integers(1, 3)), 0.08)
    return add_grain(pt.img, rng, 3.0, 5.0, 15.0)


def _vehicle_top(rng, cls, l, w, body) -> np.ndarray:
    """Roof seen from above: front at the last column, the body's left at row 0."""
    pt = Painter(l, w, BODY_RES_M, shade(body, 1.05))
    for x in np.arange(0.4, l - 0.4, 0.9):  # roof panels
        pt.line(x, 0.05 * w, x, 0.95 * w, shade(body, 0.75), 0.02)
    if cls == ObjectClass.BUS:
        pt.rect(0.35 * l, 0.25 * w, 0.55 * l, 0.75 * w, (150, 150, 150))
    marks(pt, rng, 0.05 * l, 0.1 * w, 0.9 * l, 0.8 * w, int(rng.integers(1, 4)), 0.1)
    return add_grain(pt.img, rng, 3.0, 5.0, 20.0)




# ------------------------------------------------------------------ cars: body + cabin
CAR_DECK, CABIN_L, CABIN_W, CABIN_DX = 0.52, 0.5, 0.86, -0.06  # fractions of h, l, w, l


def _car_lower_side(rng, l, h, body) -> np.ndarray:
    """Left side of a car's lower box (front at column 0): wheels, doors, handles, sill."""
    pt = Painter(l, h, BODY_RES_M, body)
    r = min(0.32, 0.45 * h)
    pt.rect(0, 0, l, 0.45 * r, (25, 25, 27))
    pt.rect(0, 0.45 * r, l, 0.45 * r + 0.1, shade(body, 0.55))
    door0, door1 = (0.5 + CABIN_DX - CABIN_L / 2) * l, (0.5 + CABIN_DX + CABIN_L / 2) * l  # under the cabin
    for x in (door0, (door0 + door1) / 2, door1):
        pt.line(l - x, 0.45 * r + 0.1, l - x, h - 0.03, shade(body, 0.45), 0.015)
    for x in (door0 + 0.12 * l, (door0 + door1) / 2 + 0.12 * l):
        pt.rect(l - x - 0.2, h - 0.14, l - x, h - 0.09, shade(body, 0.4))
    pt.rect(0.04, h - 0.16, 0.14, h - 0.1, (30, 120, 230))  # side marker
    pt.line(0, h - 0.06, l, h - 0.06, shade(body, 1.2), 0.03)  # shoulder line catches the sky
    for a in (0.17, 0.8):
        _wheel(pt, a * l, r)
    marks(pt, rng, 0.1 * l, r, 0.9 * l, h - 0.15, int(rng.integers(2, 6)), 0.1)
    return add_grain(pt.img, rng, 3.0, 6.0, 20.0)


def _cabin_side(rng, l, h, body) -> np.ndarray:
    """Left side of the cabin: raked A and C pillars, side glass with a B pillar."""
    pt = Painter(l, h, BODY_RES_M, body)
    a, c = 0.3 * l, 0.22 * l  # the windscreen's and rear window's rake in plan
    glass(pt, rng, 0, 0.1 * h, l, 0.88 * h)
    pt.poly([(0, 0.1 * h), (a, 0.88 * h), (0, 0.88 * h)], body)  # behind the windscreen: A pillar
    pt.poly([(l, 0.1 * h), (l - c, 0.88 * h), (l, 0.88 * h)], body)
    pt.line(0.04, 0.1 * h, a + 0.04, 0.88 * h, shade(body, 0.8), 0.06)
    pt.line(l - 0.04, 0.1 * h, l - c - 0.04, 0.88 * h, shade(body, 0.8), 0.1)
    pt.rect(0.5 * l - 0.06, 0.1 * h, 0.5 * l + 0.06, 0.88 * h, shade(body, 0.75))  # B pillar
    pt.rect(0, 0.88 * h, l, h, shade(body, 1.1))
    pt.rect(0, 0, l, 0.1 * h, shade(body, 0.9))
    return add_grain(pt.img, rng, 3.0, 5.0, 20.0)


def _cabin_end(rng, w, h, body, front: bool) -> np.ndarray:
    """Windscreen (front) or rear window (back) of the cabin."""
    pt = Painter(w, h, BODY_RES_M, body)
    inset = 0.06 * w
    glass(pt, rng, inset, 0.1 * h, w - inset, 0.86 * h)
    if front:
        pt.rect(w / 2 - 0.08, 0.65 * h, w / 2 + 0.08, 0.75 * h, (40, 40, 40))  # mirror
    else:
        pt.rect(w / 2 - 0.2, 0.82 * h, w / 2 + 0.2, 0.86 * h, (30, 30, 200))  # brake light
    return add_grain(pt.img, rng, 3.0, 5.0, 15.0)


def _car_deck(rng, l, w, body) -> np.ndarray:
    """Top of the lower box: bonnet (front, last columns) and boot lid, seams and a crease."""
    pt = Painter(l, w, BODY_RES_M, shade(body, 1.05))
    front_x = (0.5 + CABIN_DX + CABIN_L / 2) * l
    pt.line(front_x + 0.05, 0.05 * w, front_x + 0.05, 0.95 * w, shade(body, 0.5), 0.015)
    pt.line(front_x, 0.5 * w, l, 0.5 * w, shade(body, 0.75), 0.02)
    pt.line(0.18 * l, 0.05 * w, 0.18 * l, 0.95 * w, shade(body, 0.5), 0.015)
    marks(pt, rng, 0.6 * l, 0.1 * w, 0.95 * l, 0.8 * w, int(rng.integers(0, 3)), 0.08)
    return add_grain(pt.img, rng, 3.0, 5.0, 20.0)


def _car_roof(rng, l, w, body) -> np.ndarray:
    pt = Painter(l, w, BODY_RES_M, shade(body, 1.08))
    if rng.random() < 0.3:  # sunroof
        glass(pt, rng, 0.45 * l, 0.25 * w, 0.8 * l, 0.75 * w)
    pt.rect(0.1 * l, 0.46 * w, 0.16 * l, 0.54 * w, (25, 25, 25))  # antenna
    return add_grain(pt.img, rng, 3.0, 5.0, 20.0)


def _mirror(img: np.ndarray) -> np.ndarray:
    return img[:, ::-1].copy()


def _car(rng, l, w, h, body) -> list[Part]:
    hl = CAR_DECK * h
    lc, wc, hc = CABIN_L * l, CABIN_W * w, h - hl
    lower = {"left": _car_lower_side(rng, l, hl, body), "right": _mirror(_car_lower_side(rng, l, hl, body)),
             "front": _vehicle_end(rng, ObjectClass.CAR, w, hl, body, True, False),
             "back": _vehicle_end(rng, ObjectClass.CAR, w, hl, body, False, False), "top": _car_deck(rng, l, w, body)}
    cabin = {"left": _cabin_side(rng, lc, hc, body), "right": _mirror(_cabin_side(rng, lc, hc, body)),
             "front": _cabin_end(rng, wc, hc, body, True), "back": _cabin_end(rng, wc, hc, body, False),
             "top": _car_roof(rng, lc, wc, body)}
    return [Part(0.0, (l, w, hl), 0.0, {k: mip_levels(v) for k, v in lower.items()}),
            Part(CABIN_DX * l, (lc, wc, hc), hl, {k: mip_levels(v) for k, v in cabin.items()})]


# ------------------------------------------------------------------ people and riders
def _person(pt: Painter, cx, w, h, skin, shirt, trousers, hair, view: str) -> None:
    """A standing figure centred at x = cx in a box of width w, height h (m); view front/back/side."""
    side = view == "side"
    sw = min((0.26 if side else 0.42) * h / 1.75, 0.9 * w) / 2  # half shoulder width
    lw = 0.07 * h / 1.75
    if side:  # legs in stride
        pt.poly([(cx - 0.2, 0), (cx - 0.06, 0), (cx + 0.04, 0.48 * h), (cx - 0.08, 0.48 * h)], trousers)
        pt.poly([(cx + 0.08, 0), (cx + 0.22, 0), (cx + 0.06, 0.48 * h), (cx - 0.06, 0.48 * h)], shade(trousers, 0.8))
    else:
        for d in (-1, 1):
            pt.rect(cx + d * 0.09 - lw, 0.04 * h, cx + d * 0.09 + lw, 0.49 * h, trousers)
            pt.rect(cx + d * 0.09 - lw - 0.01, 0, cx + d * 0.09 + lw + 0.01, 0.05 * h, (25, 25, 25))
    pt.poly([(cx - 0.8 * sw, 0.47 * h), (cx + 0.8 * sw, 0.47 * h), (cx + sw, 0.82 * h), (cx - sw, 0.82 * h)], shirt)
    arm = 0.04 * h / 1.75
    for d in ((0,) if side else (-1, 1)):
        x = cx + d * (sw + arm)
        pt.rect(x - arm, 0.5 * h, x + arm, 0.81 * h, shade(shirt, 0.85))
        pt.rect(x - arm, 0.45 * h, x + arm, 0.51 * h, skin)
    pt.rect(cx - 0.04, 0.8 * h, cx + 0.04, 0.86 * h, skin)
    pt.ellipse(cx, 0.92 * h, 0.09, 0.11, skin if view != "back" else hair)
    pt.ellipse(cx + (0.03 if side else 0.0), 0.98 * h, 0.095, 0.045, hair)


def _rider_side(pt: Painter, rng, l, h, shirt, skin, helmet, motor: bool) -> None:
    """A bicycle or motorcycle with its rider, front at x = 0 (m)."""
    r = min(0.33, 0.2 * h)
    xf, xr = r + 0.02, l - r - 0.02
    for x in (xf, xr):
        pt.circle(x, r, r, TYRE, 0.09 if motor else 0.05)
        pt.circle(x, r, 0.08, (140, 140, 140))
        for a in np.linspace(0, np.pi, 5 if motor else 9)[:-1]:
            pt.line(x - r * np.cos(a), r - r * np.sin(a), x + r * np.cos(a), r + r * np.sin(a), (120, 120, 120), 0.01)
    frame = tuple(int(v) for v in rng.integers(0, 256, 3))
    seat, head_tube, bracket = (0.62 * l, 2.6 * r), (0.3 * l, 2.8 * r), (0.5 * l, r)
    if motor:
        pt.ellipse(0.5 * l, 1.6 * r, 0.3 * l, 0.7 * r, frame)
    for a, b in ((seat, bracket), (bracket, (xr, r)), ((xr, r), seat), (seat, head_tube), (head_tube, bracket),
                 (head_tube, (xf, r))):
        pt.line(*a, *b, frame, 0.04)
    shoulder, hip = (0.38 * l, 0.8 * h), (seat[0], seat[1] + 0.08)
    pt.line(*hip, *shoulder, shirt, 0.3)
    pt.line(*hip, bracket[0] + 0.1, bracket[1] + 0.35, (60, 50, 40), 0.15)
    pt.line(bracket[0] + 0.1, bracket[1] + 0.35, bracket[0], bracket[1] - 0.05, (60, 50, 40), 0.12)
    pt.line(*shoulder, head_tube[0] - 0.05, head_tube[1] + 0.15, skin, 0.07)
    pt.circle(shoulder[0] - 0.04, 0.91 * h, 0.11, skin)
    pt.ellipse(shoulder[0] - 0.03, 0.95 * h, 0.12, 0.07 if not motor else 0.12, helmet)


def _rider_front(pt: Painter, w, h, shirt, skin, helmet, motor: bool) -> None:
    cx = w / 2
    pt.rect(cx - (0.1 if motor else 0.03), 0, cx + (0.1 if motor else 0.03), 0.42 * h, TYRE)
    pt.line(cx - 0.28, 0.58 * h, cx + 0.28, 0.58 * h, (50, 50, 50), 0.04)
    if motor:
        pt.rect(cx - 0.2, 0.3 * h, cx + 0.2, 0.55 * h, (60, 60, 60))
        pt.circle(cx, 0.5 * h, 0.08, (210, 235, 245))
    pt.poly([(cx - 0.16, 0.5 * h), (cx + 0.16, 0.5 * h), (cx + 0.2, 0.85 * h), (cx - 0.2, 0.85 * h)], shirt)
    for d in (-1, 1):
        pt.line(cx + d * 0.19, 0.82 * h, cx + d * 0.26, 0.6 * h, skin, 0.07)
        pt.rect(cx + d * 0.1 - 0.06, 0.25 * h, cx + d * 0.1 + 0.06, 0.52 * h, (60, 50, 40))
    pt.circle(cx, 0.92 * h, 0.1, skin)
    pt.ellipse(cx, 0.96 * h, 0.12, 0.07, helmet)


def _figure_textures(rng, cls, l, w, h) -> dict[str, np.ndarray]:
    """BGRA textures of a pedestrian, cyclist or motorcyclist, seen from front, back and sides."""
    skin = SKIN[rng.integers(len(SKIN))]
    shirt, trousers, hair = (CLOTHES[rng.integers(len(CLOTHES))] for _ in range(3))
    out: dict[str, np.ndarray] = {}
    for face in ("front", "back", "left", "right"):
        across = face in ("front", "back")
        width = w if across else l
        pt = Painter(width, h, BODY_RES_M, None, alpha=True)
        if cls == ObjectClass.PEDESTRIAN:
            _person(pt, width / 2, width, h, skin, shirt, trousers, hair, face if across else "side")
        elif across:
            _rider_front(pt, w, h, shirt, skin, hair, cls == ObjectClass.MOTORCYCLE)
        else:
            _rider_side(pt, rng, l, h, shirt, skin, hair, cls == ObjectClass.MOTORCYCLE)
        img = add_grain(pt.img, rng, 4.0)
        if face == "right":
            img = img[:, ::-1].copy()  # the right side shows the front at its last column
        out[face] = img
    return out


# ------------------------------------------------------------------ public
FIGURES = (ObjectClass.PEDESTRIAN, ObjectClass.CYCLIST, ObjectClass.MOTORCYCLE)


def body_parts(rng: np.random.Generator, cls: int, lwh) -> list[Part]:
    """The textured part boxes of one body of class ``cls`` (ObjectClass code) and size ``lwh`` (m)."""
    cls = ObjectClass(int(cls)) if int(cls) in ObjectClass._value2member_map_ else ObjectClass.UNKNOWN
    l, w, h = (float(v) for v in lwh)
    if cls in FIGURES:
        faces = _figure_textures(rng, cls, l, w, h)
        return [Part(0.0, (l, w, h), 0.0, {k: mip_levels(v) for k, v in faces.items()}, billboard=True)]
    body = BODY_COLOURS[rng.integers(len(BODY_COLOURS))]
    if cls == ObjectClass.CAR:
        return _car(rng, l, w, h, body)
    faces = {"left": _vehicle_side(rng, cls, l, h, body), "right": _mirror(_vehicle_side(rng, cls, l, h, body)),
             "front": _vehicle_end(rng, cls, w, h, body, True), "back": _vehicle_end(rng, cls, w, h, body, False),
             "top": _vehicle_top(rng, cls, l, w, body)}
    return [Part(0.0, (l, w, h), 0.0, {k: mip_levels(v) for k, v in faces.items()})]
