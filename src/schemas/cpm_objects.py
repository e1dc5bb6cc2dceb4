"""A CPM's perceived objects (``PerceivedObject``, ETSI TS 103 324 / CDD TS 102 894-2) to and from
v2i object columns (``schemas.standard_wire``), in the message's own frame. ``schemas.cpm`` wraps them.

Classes (v2i -> ETSI, ``CLASS_TO_CPM``; the nearest ETSI class where there is no equal one):
car -> vehicle passengerCar (5), van -> lightTruck (7), truck -> heavyTruck (8), bus -> bus (6),
motorcycle -> VRU motorcyclist / motorcycle (2), pedestrian -> VRU pedestrian / ordinary (1),
cyclist -> VRU bicyclistAndLightVruVehicle / bicyclist (1), unknown -> vehicle unknown (0).
ETSI -> v2i (``cls_of``): the class entry of highest confidence; trailer, special vehicle and
agricultural -> truck, tram -> bus, moped / motorcycle -> motorcycle, any bicyclist / light VRU
vehicle -> cyclist, a VRU cluster -> its first profile (pedestrian, cyclist, motorcycle), animals
and other objects -> unknown.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from schemas import standard_wire as sw
from schemas.classes import ObjectClass
from schemas.codec import InvalidMessage
from schemas.messages import UNKNOWN_VELOCITY_VAR

_D = np.pi / 180.0
SPEED_OUT_OF_RANGE_SIGMA = 2.0  # m/s: a speed confidence "outOfRange" / "unavailable" is read as this
POSITION_UNKNOWN_SIGMA = 100.0  # m: a coordinate confidence "outOfRange" / "unavailable"
DIRECTION_UNKNOWN_SIGMA = 0.5  # rad: a polar velocity direction of unavailable confidence
POSITION_LIMIT = 131070  # 0.01 m codes; 131071 / -131072 mean out of range
VEHICLE_SUBCLASSES = frozenset({0, 5, 6, 7, 8, 9, 10, 11, 14})  # what ObjectClass.vehicleSubClass allows

CLASS_TO_CPM: dict[int, tuple[str, Any]] = {
    ObjectClass.UNKNOWN: ("vehicleSubClass", 0), ObjectClass.CAR: ("vehicleSubClass", 5),
    ObjectClass.VAN: ("vehicleSubClass", 7), ObjectClass.TRUCK: ("vehicleSubClass", 8),
    ObjectClass.BUS: ("vehicleSubClass", 6), ObjectClass.MOTORCYCLE: ("vruSubClass", ("motorcyclist", 2)),
    ObjectClass.PEDESTRIAN: ("vruSubClass", ("pedestrian", 1)),
    ObjectClass.CYCLIST: ("vruSubClass", ("bicyclistAndLightVruVehicle", 1)),
}
_VEHICLE_TO_V2I = {5: ObjectClass.CAR, 6: ObjectClass.BUS, 7: ObjectClass.VAN, 8: ObjectClass.TRUCK,
                   9: ObjectClass.TRUCK, 10: ObjectClass.TRUCK, 11: ObjectClass.BUS, 14: ObjectClass.TRUCK}
_VRU_TO_V2I = {"pedestrian": ObjectClass.PEDESTRIAN, "bicyclistAndLightVruVehicle": ObjectClass.CYCLIST,
               "motorcyclist": ObjectClass.MOTORCYCLE}
_CLUSTER_TO_V2I = (ObjectClass.PEDESTRIAN, ObjectClass.CYCLIST, ObjectClass.MOTORCYCLE, ObjectClass.UNKNOWN)
# componentsIncludedIntheMatrix bits (0 = most significant of 13)
_X, _Y, _VX, _VY = 0, 1, 3, 4


# ---------------------------------------------------------------- encode


def _codes(v: np.ndarray, step: float, lo: int, hi: int) -> list[int]:
    """Integer codes round(v / step) saturated to [lo, hi] (the standard's out-of-range codes)."""
    return np.clip(np.rint(v / step), lo, hi).astype(np.int64).tolist()


def _confidence(var: np.ndarray, step: float, hi: int) -> list[int]:
    """95 % confidence codes: ceil(1.96 sigma / step) in [1, hi] (hi: out of range)."""
    return np.clip(np.ceil(sw.Z95 * np.sqrt(np.maximum(var, 0.0)) / step - 1e-9), 1, hi).astype(np.int64).tolist()


def _rho(cov: np.ndarray, vx: np.ndarray, vy: np.ndarray) -> list[int]:
    """Correlation in percent: rho = cov / sqrt(var_x var_y)."""
    den = np.sqrt(np.maximum(vx, 0.0) * np.maximum(vy, 0.0))
    rho = np.divide(cov, den, out=np.zeros_like(cov), where=den > 0)
    return np.clip(np.rint(100.0 * rho), -100, 100).astype(np.int64).tolist()


def check_columns(c: dict[str, np.ndarray], n: int) -> None:
    """InvalidMessage for what a CPM cannot carry: > 255 objects, a non-finite value, a position
    beyond +-1310.7 m."""
    if n > 255:
        raise InvalidMessage(f"objects: {n} objects, a CPM carries at most 255", "objects")
    for name, col in c.items():
        if not np.isfinite(col).all():
            raise InvalidMessage(f"objects.{int(np.flatnonzero(~np.isfinite(col))[0])}.{name} is not finite",
                                 f"objects.{name}")
    for name in ("x", "y", "z"):
        bad = np.abs(np.rint(c[name] / 0.01)) > POSITION_LIMIT
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidMessage(f"objects.{i}.{name} = {c[name][i]} is beyond the CPM's +-1310.7 m", f"objects.{i}.{name}")


def code_columns(c: dict[str, np.ndarray]) -> dict[str, list]:
    """Per-column integer codes (lists) of object columns."""
    vknown = (c["cov_vxx"] < UNKNOWN_VELOCITY_VAR) | (c["cov_vyy"] < UNKNOWN_VELOCITY_VAR)
    # zAngle: counter-clockwise from x in [0, 360) degrees, 0.1 degree
    yaw = np.mod(np.rint(np.mod(c["yaw"], 2 * np.pi) / (0.1 * _D)), 3600)
    return {
        "id": np.mod(c["id"], 65536).astype(np.int64).tolist(), "cls": c["cls"].astype(np.int64).tolist(),
        "x": _codes(c["x"], 0.01, -131072, 131071), "y": _codes(c["y"], 0.01, -131072, 131071),
        "z": _codes(c["z"], 0.01, -131072, 131071),
        "cx": _confidence(c["cov_xx"], 0.01, 4095), "cy": _confidence(c["cov_yy"], 0.01, 4095),
        "rho": _rho(c["cov_xy"], c["cov_xx"], c["cov_yy"]), "rhov": _rho(c["cov_vxy"], c["cov_vxx"], c["cov_vyy"]),
        "vknown": vknown.tolist(), "vx": _codes(c["vx"], 0.01, -16383, 16382), "vy": _codes(c["vy"], 0.01, -16383, 16382),
        "cvx": _confidence(c["cov_vxx"], 0.01, 126), "cvy": _confidence(c["cov_vyy"], 0.01, 126),
        "ax": _codes(c["ax"], 0.1, -160, 160), "ay": _codes(c["ay"], 0.1, -160, 160),
        "yaw": yaw.astype(np.int64).tolist(), "yaw_rate": _codes(c["yaw_rate"], _D, -255, 255),
        "length": _codes(c["length"], 0.1, 1, 255), "width": _codes(c["width"], 0.1, 1, 255),
        "height": _codes(c["height"], 0.1, 1, 255), "age": _codes(c["age_s"], 0.001, 0, 2047),
        "quality": _codes(c["confidence"], 1 / 15, 0, 15),
    }


def _correlations(rho: int, rho_v: int, velocity: bool) -> list[dict]:
    """Position (x, y) and velocity (vx, vy) correlations as one lower-triangular matrix; [] if all 0."""
    if not rho and not (velocity and rho_v):
        return []
    if not velocity:  # components x, y: one column [rho]
        return [{"componentsIncludedIntheMatrix": (b"\xc0\x00", 13), "matrix": [[rho]]}]
    # components x, y, vx, vy: columns [rho(x,y), rho(x,vx), rho(x,vy)], [rho(y,vx), rho(y,vy)], [rho(vx,vy)]
    return [{"componentsIncludedIntheMatrix": (b"\xd8\x00", 13), "matrix": [[rho, 0, 0], [0, 0], [rho_v]]}]


def object_of(c: dict[str, list], i: int, delta_ms: int) -> dict:
    """One PerceivedObject of the per-column code lists ``c``."""
    obj: dict[str, Any] = {
        "objectId": c["id"][i], "measurementDeltaTime": delta_ms,
        "position": {"xCoordinate": {"value": c["x"][i], "confidence": c["cx"][i]},
                     "yCoordinate": {"value": c["y"][i], "confidence": c["cy"][i]}},
        "angles": {"zAngle": {"value": c["yaw"][i], "confidence": 127}},
        "objectDimensionZ": {"value": c["height"][i], "confidence": 32},
        "objectDimensionY": {"value": c["width"][i], "confidence": 32},
        "objectDimensionX": {"value": c["length"][i], "confidence": 32},
        "objectAge": c["age"][i], "objectPerceptionQuality": c["quality"][i],
        "classification": [{"objectClass": CLASS_TO_CPM.get(c["cls"][i], ("vehicleSubClass", 0)), "confidence": 101}],
    }
    if c["z"][i]:
        obj["position"]["zCoordinate"] = {"value": c["z"][i], "confidence": 4096}
    if c["vknown"][i]:
        obj["velocity"] = ("cartesianVelocity", {"xVelocity": {"value": c["vx"][i], "confidence": c["cvx"][i]},
                                                 "yVelocity": {"value": c["vy"][i], "confidence": c["cvy"][i]}})
    if c["ax"][i] or c["ay"][i]:
        obj["acceleration"] = ("cartesianAcceleration", {"xAcceleration": {"value": c["ax"][i], "confidence": 102},
                                                         "yAcceleration": {"value": c["ay"][i], "confidence": 102}})
    if c["yaw_rate"][i]:
        obj["zAngularVelocity"] = {"value": c["yaw_rate"][i], "confidence": "unavailable"}
    matrices = _correlations(c["rho"][i], c["rhov"][i], c["vknown"][i])
    if matrices:
        obj["lowerTriangularCorrelationMatrices"] = matrices
    return obj


# ---------------------------------------------------------------- decode


def cls_of(classification: list | None) -> int:
    """The v2i class of a classification list: its entry of highest confidence (101, unavailable,
    counts as 0; ``read_objects`` has refused a vehicleSubClass the standard does not allow)."""
    if not classification:
        return int(ObjectClass.UNKNOWN)
    best = max(classification, key=lambda e: 0 if e["confidence"] == 101 else e["confidence"])
    kind, value = best["objectClass"]
    if kind == "vehicleSubClass":
        return int(_VEHICLE_TO_V2I.get(value, ObjectClass.UNKNOWN))
    if kind == "vruSubClass":
        return int(_VRU_TO_V2I.get(value[0], ObjectClass.UNKNOWN))
    if kind == "groupSubClass" and "clusterProfiles" in value:
        data, nbits = value["clusterProfiles"]
        bits = int.from_bytes(data, "big") >> (len(data) * 8 - nbits)
        for k in range(4):
            if bits & (1 << (3 - k)):
                return int(_CLUSTER_TO_V2I[k])
    return int(ObjectClass.UNKNOWN)


def _sigma(conf: int, step: float, out_of_range: int, fallback: float) -> float:
    """sigma of a 95 % confidence code (conf * step / 1.96); ``fallback`` when out of range or unavailable."""
    return fallback if conf >= out_of_range else conf * step / sw.Z95


def _rhos(obj: dict, cartesian_velocity: bool) -> tuple[float, float]:
    """(rho_xy, rho_vxvy) from the object's correlation matrices (fraction; 0 where absent)."""
    rho, rho_v = 0.0, 0.0
    for m in obj.get("lowerTriangularCorrelationMatrices") or ():
        data, nbits = m["componentsIncludedIntheMatrix"]
        bits = int.from_bytes(data, "big") >> (len(data) * 8 - nbits)
        included = [k for k in range(nbits) if bits & (1 << (nbits - 1 - k))]
        rho = _cell(m["matrix"], included, _X, _Y) if rho == 0.0 else rho
        if cartesian_velocity and rho_v == 0.0:
            rho_v = _cell(m["matrix"], included, _VX, _VY)
    return rho, rho_v


def _cell(matrix: list[list[int]], included: list[int], a: int, b: int) -> float:
    """Correlation of components a < b: column of a, row b's place after a; 0 when absent or unavailable."""
    if a not in included or b not in included:
        return 0.0
    j, k = included.index(a), included.index(b) - included.index(a) - 1
    value = matrix[j][k] if j < len(matrix) and k < len(matrix[j]) else 101
    return 0.0 if value == 101 else value / 100.0


def _velocity(cols: dict[str, np.ndarray], i: int, obj: dict) -> bool:
    """Velocity and its covariance; False when it is unavailable (left unknown)."""
    kind, vel = obj.get("velocity", (None, None))
    if kind == "cartesianVelocity":
        vx, vy = vel["xVelocity"], vel["yVelocity"]
        if vx["value"] == 16383 or vy["value"] == 16383:
            return False
        cols["vx"][i], cols["vy"][i] = vx["value"] * 0.01, vy["value"] * 0.01
        svx = _sigma(vx["confidence"], 0.01, 126, SPEED_OUT_OF_RANGE_SIGMA)
        svy = _sigma(vy["confidence"], 0.01, 126, SPEED_OUT_OF_RANGE_SIGMA)
        cols["cov_vxx"][i], cols["cov_vyy"][i] = svx * svx, svy * svy
        return True
    if kind == "polarVelocity":  # magnitude, direction counter-clockwise from x: converted to x / y
        speed, direction = vel["velocityMagnitude"], vel["velocityDirection"]
        if speed["speedValue"] == 16383 or (direction["value"] >= 3600 and speed["speedValue"] != 0):
            return False
        s, h = speed["speedValue"] * 0.01, (direction["value"] % 3600) * 0.1 * _D
        cols["vx"][i], cols["vy"][i] = s * np.cos(h), s * np.sin(h)
        ss = _sigma(speed["speedConfidence"], 0.01, 126, SPEED_OUT_OF_RANGE_SIGMA)
        sh = _sigma(direction["confidence"], 0.1 * _D, 126, DIRECTION_UNKNOWN_SIGMA)
        # C = J diag(ss^2, (s sh)^2) J^T, J = [[cos h, -sin h], [sin h, cos h]]
        a, b = ss * ss, (s * sh) ** 2
        c_, s_ = np.cos(h), np.sin(h)
        cols["cov_vxx"][i] = c_ * c_ * a + s_ * s_ * b
        cols["cov_vyy"][i] = s_ * s_ * a + c_ * c_ * b
        cols["cov_vxy"][i] = c_ * s_ * (a - b)
        return True
    return False


def _acceleration(obj: dict) -> tuple[float, float]:
    kind, acc = obj.get("acceleration", (None, None))
    if kind == "cartesianAcceleration":
        ax, ay = acc["xAcceleration"]["value"], acc["yAcceleration"]["value"]
        return (0.0 if ax == 161 else ax * 0.1), (0.0 if ay == 161 else ay * 0.1)
    if kind == "polarAcceleration":
        m, d = acc["accelerationMagnitude"]["accelerationMagnitudeValue"], acc["accelerationDirection"]["value"]
        if m == 161 or d >= 3600:
            return 0.0, 0.0
        return m * 0.1 * np.cos(d * 0.1 * _D), m * 0.1 * np.sin(d * 0.1 * _D)
    return 0.0, 0.0


def _fill(cols: dict[str, np.ndarray], i: int, obj: dict) -> None:
    """Row ``i`` of the object columns (own frame) from one decoded PerceivedObject."""
    pos = obj["position"]
    cols["id"][i] = obj.get("objectId", i)
    cols["x"][i], cols["y"][i] = pos["xCoordinate"]["value"] * 0.01, pos["yCoordinate"]["value"] * 0.01
    cols["z"][i] = pos["zCoordinate"]["value"] * 0.01 if "zCoordinate" in pos else 0.0
    sx = _sigma(pos["xCoordinate"]["confidence"], 0.01, 4095, POSITION_UNKNOWN_SIGMA)
    sy = _sigma(pos["yCoordinate"]["confidence"], 0.01, 4095, POSITION_UNKNOWN_SIGMA)
    cartesian = _velocity(cols, i, obj) and obj["velocity"][0] == "cartesianVelocity"
    rho, rho_v = _rhos(obj, cartesian)
    cols["cov_xx"][i], cols["cov_yy"][i], cols["cov_xy"][i] = sx * sx, sy * sy, rho * sx * sy
    if cartesian:
        cols["cov_vxy"][i] = rho_v * np.sqrt(cols["cov_vxx"][i] * cols["cov_vyy"][i])
    cols["ax"][i], cols["ay"][i] = _acceleration(obj)
    yaw_code = obj["angles"]["zAngle"]["value"] if "angles" in obj else 3601
    cols["yaw"][i] = 0.0 if yaw_code >= 3600 else ((yaw_code * 0.1 + 180.0) % 360.0 - 180.0) * _D
    rate = obj.get("zAngularVelocity", {"value": 0})["value"]
    cols["yaw_rate"][i] = 0.0 if rate == 256 else rate * _D
    for name, key in (("length", "objectDimensionX"), ("width", "objectDimensionY"), ("height", "objectDimensionZ")):
        if key in obj and obj[key]["value"] != 256:
            cols[name][i] = obj[key]["value"] * 0.1
    cols["age_s"][i] = obj.get("objectAge", 0) * 0.001
    cols["confidence"][i] = obj.get("objectPerceptionQuality", 15) / 15.0
    cols["cls"][i] = cls_of(obj.get("classification"))


def read_objects(objects: list[dict], skipped: Counter,
                 beyond: list[dict] | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(object columns in the message's frame, measurementDeltaTime per object) of decoded
    PerceivedObjects. An object without the objectId the container requires gets its index (counted);
    one whose x or y is only "out of range" (beyond +-1310.70 m) cannot be placed: left out,
    counted in ``skipped`` and listed in ``beyond`` (id, x_m, y_m: the range's bound, m)."""
    keep = []
    for k, obj in enumerate(objects):
        if "objectId" not in obj:  # required by the container (WITH COMPONENTS objectId PRESENT): its index
            skipped["object_id_absent"] += 1
        for entry in obj.get("classification") or ():
            kind, value = entry["objectClass"]
            if kind == "vehicleSubClass" and value not in VEHICLE_SUBCLASSES:
                raise InvalidMessage(f"cpm vehicleSubClass {value} is not allowed (0, 5..11, 14)",
                                     f"perceivedObjects.{k}.classification")
        xy = (obj["position"]["xCoordinate"]["value"], obj["position"]["yCoordinate"]["value"])
        if any(v in (-131072, 131071) for v in xy):
            skipped["object_position_out_of_range"] += 1
            if beyond is not None:
                beyond.append({"id": obj.get("objectId", k), "x_m": xy[0] / 100, "y_m": xy[1] / 100})
            continue
        for key in ("mapPosition", "sensorIdList"):
            if key in obj:
                skipped[f"object_{key}"] += 1
        keep.append(obj)
    cols = sw.empty_columns(len(keep))
    for i, obj in enumerate(keep):
        _fill(cols, i, obj)
    return cols, np.array([o["measurementDeltaTime"] for o in keep], dtype=np.int64)
