"""The ``map`` frame as a local east-north-up (ENU) tangent plane on the WGS84 ellipsoid.

x east, y north, metres, in the plane tangent to the ellipsoid at the site's origin (latitude,
longitude in degrees, height 0): the projection of GeographicLib's ``LocalCartesian`` (Lanelet2's
``LocalCartesianProjector``, which v2i uses for a site's map), so that a CPM's WGS84 reference
position and a site's map agree. Closed form (geodetic -> ECEF -> ENU, and back with Bowring's
latitude iteration); heights are taken as 0.
"""

from __future__ import annotations

import math

A = 6_378_137.0  # WGS84 semi-major axis (m)
F = 1 / 298.257223563  # WGS84 flattening
E2 = F * (2 - F)  # first eccentricity squared


def _ecef(lat_deg: float, lon_deg: float, h: float = 0.0) -> tuple[float, float, float]:
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    n = A / math.sqrt(1 - E2 * math.sin(lat) ** 2)  # prime vertical radius
    return ((n + h) * math.cos(lat) * math.cos(lon), (n + h) * math.cos(lat) * math.sin(lon),
            (n * (1 - E2) + h) * math.sin(lat))


def geo_to_enu(lat_deg: float, lon_deg: float, origin: tuple[float, float]) -> tuple[float, float]:
    """(east, north) metres of a WGS84 point in the tangent plane at ``origin`` (lat, lon deg)."""
    x, y, z = _ecef(lat_deg, lon_deg)
    x0, y0, z0 = _ecef(*origin)
    dx, dy, dz = x - x0, y - y0, z - z0
    lat0, lon0 = math.radians(origin[0]), math.radians(origin[1])
    east = -math.sin(lon0) * dx + math.cos(lon0) * dy
    north = (-math.sin(lat0) * math.cos(lon0) * dx - math.sin(lat0) * math.sin(lon0) * dy
             + math.cos(lat0) * dz)
    return east, north


def enu_to_geo(east: float, north: float, origin: tuple[float, float]) -> tuple[float, float]:
    """(lat, lon) degrees of the point of the tangent plane at ``origin`` at (east, north), up 0:
    the inverse of ``geo_to_enu`` (to < 1 mm within tens of km; the plane's point is above the
    ellipsoid by d^2 / 2R, 8 cm at 1 km, which only moves the height)."""
    lat0, lon0 = math.radians(origin[0]), math.radians(origin[1])
    x0, y0, z0 = _ecef(*origin)
    up = 0.0
    # ENU -> ECEF: the transpose of the rotation above
    x = x0 - math.sin(lon0) * east - math.sin(lat0) * math.cos(lon0) * north + math.cos(lat0) * math.cos(lon0) * up
    y = y0 + math.cos(lon0) * east - math.sin(lat0) * math.sin(lon0) * north + math.cos(lat0) * math.sin(lon0) * up
    z = z0 + math.cos(lat0) * north + math.sin(lat0) * up
    p = math.hypot(x, y)
    lat = math.atan2(z, p * (1 - E2))
    for _ in range(5):  # lat = atan((z + e^2 N sin lat) / p)
        n = A / math.sqrt(1 - E2 * math.sin(lat) ** 2)
        lat = math.atan2(z + E2 * n * math.sin(lat), p)
    return math.degrees(lat), math.degrees(math.atan2(y, x))
