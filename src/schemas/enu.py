"""The ``map`` frame as a local east-north-up (ENU) tangent plane on the WGS84 ellipsoid.

x east, y north, metres, in the plane tangent to the ellipsoid at the site's origin (latitude,
longitude in degrees, height 0): the projection of GeographicLib's ``LocalCartesian`` (Lanelet2's
``LocalCartesianProjector``, which v2i uses for a site's map), so that a CPM's WGS84 reference
position and a site's map agree. Closed form (geodetic -> ECEF -> ENU, and back with Bowring's
latitude iteration); heights are taken as 0.
"""

from __future__ import annotations

import math

import numpy as np

A = 6_378_137.0  # WGS84 semi-major axis (m)
F = 1 / 298.257223563  # WGS84 flattening
E2 = F * (2 - F)  # first eccentricity squared


def _ecef(lat_deg, lon_deg, h=0.0):
    """ECEF (x, y, z) metres of geodetic points (degrees; floats or arrays)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = A / np.sqrt(1 - E2 * np.sin(lat) ** 2)  # prime vertical radius
    return ((n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
            (n * (1 - E2) + h) * np.sin(lat))


def _to_enu(x, y, z, origin: tuple[float, float]):
    """(east, north, up) in the tangent frame at ``origin`` of ECEF points."""
    x0, y0, z0 = _ecef(*origin)
    dx, dy, dz = x - x0, y - y0, z - z0
    lat0, lon0 = math.radians(origin[0]), math.radians(origin[1])
    east = -math.sin(lon0) * dx + math.cos(lon0) * dy
    north = -math.sin(lat0) * math.cos(lon0) * dx - math.sin(lat0) * math.sin(lon0) * dy + math.cos(lat0) * dz
    up = math.cos(lat0) * math.cos(lon0) * dx + math.cos(lat0) * math.sin(lon0) * dy + math.sin(lat0) * dz
    return east, north, up


def _from_enu(east, north, up, origin: tuple[float, float]):
    """ECEF of points given in the tangent frame at ``origin`` (the transpose of ``_to_enu``'s rotation)."""
    lat0, lon0 = math.radians(origin[0]), math.radians(origin[1])
    x0, y0, z0 = _ecef(*origin)
    x = x0 - math.sin(lon0) * east - math.sin(lat0) * math.cos(lon0) * north + math.cos(lat0) * math.cos(lon0) * up
    y = y0 + math.cos(lon0) * east - math.sin(lat0) * math.sin(lon0) * north + math.cos(lat0) * math.sin(lon0) * up
    z = z0 + math.cos(lat0) * north + math.sin(lat0) * up
    return x, y, z


def between(east, north, source: tuple[float, float], target: tuple[float, float]):
    """(east, north) in the tangent plane at ``target`` of points (arrays) of the plane at ``source``
    (exact: through ECEF; the up they get is dropped)."""
    e, n, _ = _to_enu(*_from_enu(np.asarray(east, float), np.asarray(north, float), 0.0, source), target)
    return e, n


def geo_to_enu(lat_deg: float, lon_deg: float, origin: tuple[float, float]) -> tuple[float, float]:
    """(east, north) metres of a WGS84 point in the tangent plane at ``origin`` (lat, lon deg)."""
    east, north, _ = _to_enu(*_ecef(lat_deg, lon_deg), origin)
    return float(east), float(north)


def enu_to_geo(east: float, north: float, origin: tuple[float, float]) -> tuple[float, float]:
    """(lat, lon) degrees of the point of the tangent plane at ``origin`` at (east, north), up 0:
    the inverse of ``geo_to_enu`` (to < 1 mm within tens of km; the plane's point is above the
    ellipsoid by d^2 / 2R, 8 cm at 1 km, which only moves the height)."""
    x, y, z = (float(v) for v in _from_enu(east, north, 0.0, origin))
    p = math.hypot(x, y)
    lat = math.atan2(z, p * (1 - E2))
    for _ in range(5):  # lat = atan((z + e^2 N sin lat) / p)
        n = A / math.sqrt(1 - E2 * math.sin(lat) ** 2)
        lat = math.atan2(z + E2 * n * math.sin(lat), p)
    return math.degrees(lat), math.degrees(math.atan2(y, x))
