"""CPM and SDSM object lists (schemas.cpm, schemas.sdsm, schemas.list_wire): round trips at the
standard's resolution, header mapping, limits, and hostile bytes only ever giving CodecErrors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import cpm, its_time, list_wire, sdsm
from schemas import cpm_objects
from schemas import standard_wire as sw
from schemas.codec import CodecError, InvalidMessage, MessageTooLarge
from schemas.messages import UNKNOWN_VELOCITY_VAR, ObjectList, ObjectListHeader

T0 = 1_767_225_600_123_456_789
REASONS = {"malformed", "invalid", "too_large", "wrong_type", "version"}


def _header(seq: int = 41, prediction_ns: int = 0) -> ObjectListHeader:
    return ObjectListHeader(rsu_id="rsu-a", seq=seq, capture_time_ns=T0, publish_time_ns=T0 + 87_654_321,
                            prediction_ns=prediction_ns)


def _columns(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    cols = sw.empty_columns(n)
    cols.update(
        id=rng.integers(0, 60000, n).astype(float), cls=rng.integers(0, 8, n).astype(float),
        x=rng.uniform(-900, 900, n), y=rng.uniform(-900, 900, n), length=rng.uniform(0.5, 12, n),
        width=rng.uniform(0.5, 3, n), height=rng.uniform(1.0, 4, n), yaw=rng.uniform(-math.pi, math.pi, n),
        vx=rng.uniform(-30, 30, n), vy=rng.uniform(-30, 30, n), ax=rng.uniform(-5, 5, n), ay=rng.uniform(-5, 5, n),
        yaw_rate=rng.uniform(-1, 1, n), cov_xx=rng.uniform(0.01, 4, n), cov_yy=rng.uniform(0.01, 4, n),
        cov_vxx=rng.uniform(0.001, 0.09, n), cov_vyy=rng.uniform(0.001, 0.09, n), confidence=rng.uniform(0, 1, n),
        age_s=rng.uniform(0, 2, n),
    )
    cols["cov_xy"] = rng.uniform(-0.9, 0.9, n) * np.sqrt(cols["cov_xx"] * cols["cov_yy"])
    cols["cov_vxy"] = rng.uniform(-0.9, 0.9, n) * np.sqrt(cols["cov_vxx"] * cols["cov_vyy"])
    return cols


def _angle_err(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def test_cpm_round_trip_within_its_resolution() -> None:
    cols = _columns(np.random.default_rng(3), 60)
    header, out = cpm.decode(cpm.encode(_header(prediction_ns=40_000_000), cols), "rsu-a")
    # referenceTime = publish (TAI), each object at capture + prediction: the header's capture is that
    # time, prediction 0, and seq 8 x the reference time in ms (a CPM has no sequence number)
    assert (header.rsu_id, header.seq, header.prediction_ns) == ("rsu-a", 8 * its_time.its_ms(T0 + 87_654_321), 0)
    assert header.capture_time_ns == T0 - 456_789 + 40_000_000 and header.publish_time_ns == T0 - 456_789 + 88_000_000
    np.testing.assert_array_equal(out["id"], cols["id"])
    np.testing.assert_array_equal(out["cls"], cols["cls"])
    for name, tol in (("x", 0.005), ("y", 0.005), ("vx", 0.005), ("vy", 0.005), ("ax", 0.05), ("ay", 0.05),
                      ("length", 0.05), ("width", 0.05), ("height", 0.05), ("age_s", 0.0005), ("confidence", 1 / 30)):
        assert np.abs(out[name] - cols[name]).max() <= tol + 1e-9, name
    assert _angle_err(out["yaw"], cols["yaw"]).max() <= math.radians(0.05) + 1e-9
    assert np.abs(out["yaw_rate"] - cols["yaw_rate"]).max() <= math.radians(0.5) + 1e-9
    # sigma = conf * 0.01 / 1.96 with conf = ceil(1.96 sigma / 0.01): at most 0.0051 m more, never less
    for var in ("cov_xx", "cov_yy", "cov_vxx", "cov_vyy"):
        d_sigma = np.sqrt(out[var]) - np.sqrt(cols[var])
        assert d_sigma.min() >= -1e-9 and d_sigma.max() <= 0.01 / sw.Z95 + 1e-9, var
    rho_in = cols["cov_xy"] / np.sqrt(cols["cov_xx"] * cols["cov_yy"])
    rho_out = out["cov_xy"] / np.sqrt(out["cov_xx"] * out["cov_yy"])
    assert np.abs(rho_out - rho_in).max() <= 0.005 + 1e-9


def test_cpm_unknown_velocity_and_wide_speed_confidence() -> None:
    cols = _columns(np.random.default_rng(4), 2)
    cols["cov_vxx"][0] = cols["cov_vyy"][0] = UNKNOWN_VELOCITY_VAR  # not measured: no velocity sent
    cols["cov_vxx"][1] = cols["cov_vyy"][1] = 4.0  # 95 % bound 3.9 m/s > 1.25: outOfRange
    _, out = cpm.decode(cpm.encode(_header(), cols))
    assert out["vx"][0] == 0.0 and out["cov_vxx"][0] == UNKNOWN_VELOCITY_VAR
    assert out["cov_vxx"][1] == pytest.approx(cpm_objects.SPEED_OUT_OF_RANGE_SIGMA**2)


def test_sdsm_round_trip_within_its_resolution() -> None:
    cols = _columns(np.random.default_rng(5), 40)
    header, out = sdsm.decode(sdsm.encode(_header(seq=300, prediction_ns=40_000_000), cols), "rsu-a")
    assert (header.seq, header.prediction_ns, header.capture_time_ns) == (300, 40_000_000, T0 - 456_789)
    assert np.abs(out["x"] - cols["x"]).max() <= 0.05 + 1e-9 and np.abs(out["y"] - cols["y"]).max() <= 0.05 + 1e-9
    np.testing.assert_array_equal(out["id"], cols["id"])
    # the velocity survives as speed along the heading (its direction when moving)
    assert np.abs(out["vx"] - cols["vx"]).max() < 0.02 and np.abs(out["vy"] - cols["vy"]).max() < 0.02
    moving = np.hypot(cols["vx"], cols["vy"]) >= sdsm.MOVING_MPS
    assert _angle_err(out["yaw"][moving], np.arctan2(cols["vy"], cols["vx"])[moving]).max() < math.radians(0.01)
    assert np.all(np.sqrt(out["cov_xx"]) * sw.Z95 >= np.sqrt(np.maximum(cols["cov_xx"], cols["cov_yy"])) * sw.Z95 - 1e-9)
    vehicles = np.isin(cols["cls"], [1, 2, 3, 4, 7])
    np.testing.assert_array_equal(out["cls"], cols["cls"])
    assert np.abs(out["length"][vehicles] - cols["length"][vehicles]).max() <= 0.005 + 1e-9


def test_cpm_carries_no_private_data() -> None:
    """No v2i extension on the standard wire: seq comes from the reference time."""
    data = cpm.encode(_header(), _columns(np.random.default_rng(6), 3))
    spec = sw.compiled(cpm.ASN1_FILE)
    msg = spec.decode("CollectivePerceptionMessage", data)
    assert set(msg["payload"]["managementContainer"]) == {"referenceTime", "referencePosition"}
    header, out = cpm.decode(data)
    assert header.rsu_id == f"station{cpm.station_id('rsu-a')}"
    assert header.seq == cpm.sequence(its_time.its_ms(T0 + 87_654_321))
    assert len(out["id"]) == 3


def test_limits_and_fit() -> None:
    rng = np.random.default_rng(7)
    with pytest.raises(InvalidMessage):
        cpm.encode(_header(), _columns(rng, 256))
    far = _columns(rng, 3)
    far["x"][1] = 2000.0
    with pytest.raises(InvalidMessage):
        cpm.encode(_header(), far)
    cols, counts = list_wire.fit_standard(far, "cpm")
    assert len(cols["id"]) == 2 and counts == {"out_of_range": 1}
    cols, counts = list_wire.fit_standard(_columns(rng, 300), "sdsm")
    assert len(cols["id"]) == 255 and counts == {"truncated": 45}
    assert list_wire.encode_list(ObjectList(header=_header()), "sdsm") is None  # an SDSM carries >= 1 object
    assert list_wire.decode_list(list_wire.encode_list(ObjectList(header=_header()), "cpm"), "cpm", "rsu-a").header.seq == 8 * its_time.its_ms(T0 + 87_654_321)
    with pytest.raises(MessageTooLarge):
        cpm.decode(b"\x00" * (sw.MAX_STANDARD_BYTES + 1))


def test_list_wire_gives_the_same_objectlist_for_every_encoding() -> None:
    msg = ObjectList(header=_header(), objects=[{"id": 5, "cls": 1, "x": 12.34, "y": -5.67, "length": 4.5,
                                                     "width": 1.8, "vx": 3.21, "vy": 0.5, "cov_vxx": 0.04,
                                                     "cov_vyy": 0.04}])
    assert list_wire.list_key("cpm", "rsu-a") == "v2x/rsu/rsu-a/cpm"
    for wire in list_wire.WIRES:
        out = list_wire.decode_list(list_wire.encode_list(msg, wire), wire, "rsu-a")
        assert out.header.rsu_id == "rsu-a" and len(out.objects) == 1
        assert out.objects[0].x == pytest.approx(12.34, abs=0.05)


def _all_codec_errors(decoder, data: bytes) -> None:
    try:
        decoder(data, "rsu-a")
    except CodecError as exc:
        assert exc.reason in REASONS


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=400))
def test_random_bytes_raise_only_codec_errors(data: bytes) -> None:
    _all_codec_errors(cpm.decode, data)
    _all_codec_errors(sdsm.decode, data)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_mutated_messages_raise_only_codec_errors(draw) -> None:
    cols = _columns(np.random.default_rng(8), 4)
    for module in (cpm, sdsm):
        data = bytearray(module.encode(_header(), cols))
        for _ in range(draw.draw(st.integers(1, 6))):
            i = draw.draw(st.integers(0, len(data) - 1))
            data[i] = draw.draw(st.integers(0, 255))
        cut = draw.draw(st.integers(1, len(data)))
        _all_codec_errors(module.decode, bytes(data[:cut]))


def _target(wire: str) -> dict:
    from v2i.offline.runner import OfflineRun
    from v2i.offline.spec import RunSpec

    run = OfflineRun(RunSpec(scenario="red-light-runner", seed=1, wire=wire))
    run.execute()
    return run.report(driver="eval")["target"]


def test_a_v2i_obu_fuses_standard_rsu_lists_as_well_as_v2i_ones() -> None:
    """Issue 15: CPM (and SDSM) through a v2i OBU gives the v2i wire's target metrics within quantisation
    (v2i eval --scenario red-light-runner --seed 1: BEV IoU 0.754 / 0.7537 / 0.7514, RMSE 0.508 m)."""
    base = _target("v2i")
    for wire in ("cpm", "sdsm"):
        got = _target(wire)
        assert got["first_detection_distance_m"] == base["first_detection_distance_m"], wire
        assert got["detected_cycles"] == base["detected_cycles"] and got["id_switches"] == base["id_switches"], wire
        assert abs(got["mean_bev_iou"] - base["mean_bev_iou"]) <= 0.01, wire
        assert abs(got["rmse_m"] - base["rmse_m"]) <= 0.02, wire
