"""Zenoh key expressions of the V2X system; identical on the RSU and vehicle sides.

Ids (``rsu_id``, ``vehicle_id``, ``link_id``) are 1-64 characters of ``[A-Za-z0-9_-]``, so
they can never inject a ``/`` or a wildcard into a key expression.
"""

from __future__ import annotations

import re

ID_PATTERN = re.compile(r"^[A-Za-z0-9_-]{1,64}$")

RSU_TOPICS = ("objects", "predictions", "time", "alive", "metrics", "image_features", "cpm", "sdsm")

RSU_OBJECTS_ALL = "v2x/rsu/*/objects"
RSU_PREDICTIONS_ALL = "v2x/rsu/*/predictions"
RSU_TIME_ALL = "v2x/rsu/*/time"
RSU_ALIVE_ALL = "v2x/rsu/*/alive"
RSU_IMAGE_FEATURES_ALL = "v2x/rsu/*/image_features"
# object lists in a standard encoding (RSU --wire cpm|sdsm; schemas.cpm, schemas.sdsm)
RSU_CPM_ALL = "v2x/rsu/*/cpm"
RSU_SDSM_ALL = "v2x/rsu/*/sdsm"


def check_id(node_id: str) -> str:
    """``node_id`` unchanged if it is a valid id, else ValueError."""
    if not isinstance(node_id, str) or not ID_PATTERN.fullmatch(node_id):
        raise ValueError(f"invalid id {node_id!r}: must be 1-64 characters of A-Z a-z 0-9 _ -")
    return node_id


def _rsu(rsu_id: str, topic: str) -> str:
    return f"v2x/rsu/{check_id(rsu_id)}/{topic}"


def _obu(vehicle_id: str, topic: str) -> str:
    return f"v2x/obu/{check_id(vehicle_id)}/{topic}"


def _link(link_id: str, topic: str) -> str:
    return f"v2x/link/{check_id(link_id)}/{topic}"


def rsu_objects(rsu_id: str) -> str:
    """Object lists published by an RSU (RSU -> vehicles)."""
    return _rsu(rsu_id, "objects")


def rsu_cpm(rsu_id: str) -> str:
    """Object lists of an RSU as ETSI collective perception messages (UPER; ``schemas.cpm``)."""
    return _rsu(rsu_id, "cpm")


def rsu_sdsm(rsu_id: str) -> str:
    """Object lists of an RSU as SAE J3224 sensor data sharing messages (UPER; ``schemas.sdsm``)."""
    return _rsu(rsu_id, "sdsm")


def rsu_predictions(rsu_id: str) -> str:
    """Long-horizon predicted trajectories published by an RSU."""
    return _rsu(rsu_id, "predictions")


def rsu_time(rsu_id: str) -> str:
    """Queryable of an RSU answering NTP-style time requests."""
    return _rsu(rsu_id, "time")


def rsu_alive(rsu_id: str) -> str:
    """Liveliness token of an RSU."""
    return _rsu(rsu_id, "alive")


def rsu_metrics(rsu_id: str) -> str:
    """Periodic RSU health metrics (published, skipped, refused inputs)."""
    return _rsu(rsu_id, "metrics")


def rsu_image_features(rsu_id: str) -> str:
    """Camera frames' boxes + ORB features for image-level fusion (ROIF), RSU -> vehicles."""
    return _rsu(rsu_id, "image_features")


def obu_objects(vehicle_id: str) -> str:
    """Fused object lists published by a vehicle's OBU."""
    return _obu(vehicle_id, "objects")


def obu_metrics(vehicle_id: str) -> str:
    """Periodic OBU health metrics."""
    return _obu(vehicle_id, "metrics")


def obu_planning(vehicle_id: str) -> str:
    """Planner-facing output of a vehicle's OBU: RSU paths handed over in planning fusion."""
    return _obu(vehicle_id, "planning")


def obu_image_objects(vehicle_id: str) -> str:
    """Image-level fused boxes (ROIF) of a vehicle's OBU, one message per ego camera frame."""
    return _obu(vehicle_id, "image_objects")


def obu_pose(vehicle_id: str) -> str:
    """Ego pose of a vehicle in the map frame."""
    return _obu(vehicle_id, "pose")


# Sensor inputs of the services (``--source zenoh``) and the simulated world's truth
# (``schemas.sensor_messages``). Outside ``v2x/rsu/**`` and ``v2x/obu/**``, so the link
# emulator never relays them and an input can never be mistaken for an RSU's output.
WORLD_TRUTH = "v2x/world/truth"


def sensor_rsu_objects(rsu_id: str) -> str:
    """Detections of an RSU's own sensor (``SensorObjects``, frame ``map``): sensor -> RSU."""
    return f"v2x/sensor/rsu/{check_id(rsu_id)}/objects"


def sensor_vehicle_objects(vehicle_id: str) -> str:
    """Detections of a vehicle's own sensor (``SensorObjects``, frame ``base_link``): sensor -> OBU."""
    return f"v2x/sensor/vehicle/{check_id(vehicle_id)}/objects"


def sensor_vehicle_pose(vehicle_id: str) -> str:
    """A vehicle's localisation (``LocalizationPose``, map): localisation -> OBU."""
    return f"v2x/sensor/vehicle/{check_id(vehicle_id)}/pose"


def link_control(link_id: str) -> str:
    """Control channel of a link emulator."""
    return _link(link_id, "control")


def link_stats(link_id: str) -> str:
    """Statistics published by a link emulator."""
    return _link(link_id, "stats")


def rsu_id_from_key(key: str) -> str:
    """The RSU id in a concrete RSU key such as ``v2x/rsu/rsu-1/objects``; ValueError otherwise."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[:2] != ["v2x", "rsu"] or parts[3] not in RSU_TOPICS:
        raise ValueError(f"{key!r} is not an RSU key (v2x/rsu/<rsu_id>/{{{','.join(RSU_TOPICS)}}})")
    try:
        return check_id(parts[2])
    except ValueError:
        raise ValueError(f"{key!r} is not an RSU key: bad rsu id {parts[2]!r}") from None


def rsu_id_or_none(key: str) -> str | None:
    """The RSU id in an RSU key expression, None for any other key."""
    try:
        return rsu_id_from_key(key)
    except ValueError:
        return None


# V2V (``obu_service.peers``): what a vehicle sends its peers over the air. The sender's id is in
# the key, and the V2V emulator relays from a vehicle's session only its own ``v2x/v2v/{id}/**``.
V2V_OBJECTS_ALL = "v2x/v2v/*/objects"
V2V_TIME_ALL = "v2x/v2v/*/time"


def v2v_from(vehicle_id: str) -> str:
    """Everything vehicle ``vehicle_id`` sends its peers (what a V2V emulator relays from it)."""
    return f"v2x/v2v/{check_id(vehicle_id)}/**"


def v2v_objects(vehicle_id: str) -> str:
    """A vehicle's shared list: the objects its own sensors perceive (``FusedObjectList``)."""
    return f"v2x/v2v/{check_id(vehicle_id)}/objects"


def v2v_time(vehicle_id: str) -> str:
    """A vehicle's time requests to its peers (``TimeRequest``, broadcast)."""
    return f"v2x/v2v/{check_id(vehicle_id)}/time"


def v2v_time_reply(answerer: str, requester: str) -> str:
    """``answerer``'s reply (``TimeReply``) to ``requester``'s time request."""
    return f"v2x/v2v/{check_id(answerer)}/time_reply/{check_id(requester)}"


def v2v_sender(key: str) -> str:
    """The sending vehicle's id in a concrete V2V key; ValueError for any other key."""
    parts = str(key).split("/")
    if len(parts) < 4 or parts[:2] != ["v2x", "v2v"]:
        raise ValueError(f"{key!r} is not a V2V key (v2x/v2v/<vehicle_id>/...)")
    return check_id(parts[2])


def obu_peers(vehicle_id: str) -> str:
    """A vehicle's V2V peers as its OBU sees them (JSON: lists accepted, clock offset per peer)."""
    return _obu(vehicle_id, "peers")
