"""Key expressions: exact strings, id validation, RSU id extraction."""

from __future__ import annotations

import pytest

from schemas import keys


def test_key_builders() -> None:
    assert keys.rsu_objects("rsu-1") == "v2x/rsu/rsu-1/objects"
    assert keys.rsu_predictions("rsu-1") == "v2x/rsu/rsu-1/predictions"
    assert keys.rsu_time("rsu_1") == "v2x/rsu/rsu_1/time"
    assert keys.rsu_alive("R1") == "v2x/rsu/R1/alive"
    assert keys.obu_objects("car-7") == "v2x/obu/car-7/objects"
    assert keys.obu_metrics("car-7") == "v2x/obu/car-7/metrics"
    assert keys.obu_pose("car-7") == "v2x/obu/car-7/pose"
    assert keys.link_control("dsrc") == "v2x/link/dsrc/control"
    assert keys.link_stats("dsrc") == "v2x/link/dsrc/stats"


def test_wildcards() -> None:
    assert keys.RSU_OBJECTS_ALL == "v2x/rsu/*/objects"
    assert keys.RSU_PREDICTIONS_ALL == "v2x/rsu/*/predictions"
    assert keys.RSU_TIME_ALL == "v2x/rsu/*/time"


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "rsu 1", "rsü", "x" * 65, "a$b", None, 3])
@pytest.mark.parametrize(
    "builder",
    [keys.rsu_objects, keys.rsu_predictions, keys.rsu_time, keys.rsu_alive, keys.obu_objects, keys.obu_metrics,
     keys.obu_pose, keys.link_control, keys.link_stats],
)
def test_invalid_ids_are_rejected(builder, bad) -> None:
    with pytest.raises(ValueError, match="invalid id"):
        builder(bad)


def test_longest_valid_id() -> None:
    assert keys.rsu_objects("a" * 64) == f"v2x/rsu/{'a' * 64}/objects"


@pytest.mark.parametrize("builder", [keys.rsu_objects, keys.rsu_predictions, keys.rsu_time, keys.rsu_alive])
def test_rsu_id_from_key_inverts_builders(builder) -> None:
    assert keys.rsu_id_from_key(builder("rsu-A_9")) == "rsu-A_9"


@pytest.mark.parametrize(
    "key",
    [
        "v2x/obu/car-1/objects",
        "v2x/link/l1/stats",
        keys.RSU_OBJECTS_ALL,
        "v2x/rsu/rsu-1",
        "v2x/rsu/rsu-1/objects/extra",
        "v2x/rsu/rsu-1/unknown",
        "x2v/rsu/rsu-1/objects",
        "v2x/rsu//objects",
        "",
    ],
)
def test_rsu_id_from_non_rsu_key_raises(key: str) -> None:
    with pytest.raises(ValueError, match="not an RSU key"):
        keys.rsu_id_from_key(key)
