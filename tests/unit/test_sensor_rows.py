"""The sensor models build their detections from the kept rows alone: the same detections, bit for bit, as
the construction of every actor's row followed by a take of the kept ones (the references below)."""

import numpy as np
import pytest

from v2i.core.frames import map_to_base, wrap_angle
from v2i.core.objects import ObjectArray
from v2i.core.objects import diagonal_covariances as _diagonal_covariances
from v2i.sim.scenario import load_scenario
from v2i.sim.sensors import (_MIN_SIZE_M, SOURCE_RSU, SOURCE_VEHICLE, Lidar, RsuCamera, _default_lwh,
                         mean_error_at, per_axis_sigma)
from v2i.sim.world import World

COLUMNS = ("ids", "cls", "xy", "z", "lwh", "yaw", "vxy", "axy", "yaw_rate", "cov_xy", "confidence", "cov_vxy",
           "age_s", "sources")


def _lidar_before(lidar: Lidar, world: World, t_s: float) -> ObjectArray:
    c, rng = lidar.cfg, lidar.rng
    ego, gt = world.ego_at(t_s), world.actors_at(t_s)
    n = len(gt)
    detected = rng.random(n) < c.detection_probability
    dist, vis = lidar._visibility(world, gt, ego, wanted=detected)
    truth = map_to_base(gt, ego)
    xy = truth.xy + rng.normal(0.0, c.position_noise_std_m, (n, 2))
    z = truth.z + rng.normal(0.0, c.position_noise_std_m, n)
    yaw = wrap_angle(truth.yaw + rng.normal(0.0, c.yaw_noise_std_rad, n))
    lwh = np.maximum(truth.lwh + rng.normal(0.0, c.size_noise_std_m, (n, 3)), _MIN_SIZE_M)
    vxy = truth.vxy + rng.normal(0.0, c.velocity_noise_std_mps, (n, 2))
    confidence = np.clip(vis * (1.0 - 0.5 * dist / c.range_m), 0.05, 1.0)
    keep = (dist <= c.range_m) & (vis >= c.min_visible_fraction) & detected
    return ObjectArray(
        ids=np.full(n, -1, dtype=np.int64), cls=truth.cls, xy=xy, z=z, lwh=lwh, yaw=yaw, vxy=vxy,
        cov_xy=np.tile(np.eye(2) * c.position_noise_std_m**2, (n, 1, 1)), confidence=confidence,
        cov_vxy=np.tile(np.eye(2) * c.velocity_noise_std_mps**2, (n, 1, 1)),
        sources=np.full(n, SOURCE_VEHICLE, dtype=np.int64)).take(keep)


def _camera_before(camera: RsuCamera, world: World, t_s: float) -> tuple[ObjectArray, float]:
    c, rng = camera.cfg, camera.rng
    delay_s = rng.uniform(*c.processing_delay_ms) / 1000.0
    truth = world.actors_at(t_s)
    rng_m, observable = camera._coverage(world, truth)
    n = len(truth)
    sigma = per_axis_sigma(mean_error_at(rng_m, c))
    detected = rng.random(n) < c.detection_probability
    xy = truth.xy + rng.normal(0.0, 1.0, (n, 2)) * sigma[:, None]
    yaw = wrap_angle(truth.yaw + rng.normal(0.0, c.yaw_noise_std_rad, n))
    lwh = np.maximum(_default_lwh(truth.cls) + rng.normal(0.0, c.size_noise_std_m, (n, 3)), _MIN_SIZE_M)
    out = ObjectArray(
        ids=np.full(n, -1, dtype=np.int64), cls=truth.cls, xy=xy, z=lwh[:, 2] / 2.0, lwh=lwh, yaw=yaw,
        vxy=np.zeros((n, 2)), cov_xy=sigma[:, None, None] ** 2 * np.eye(2),
        confidence=np.clip(1.0 - 0.5 * rng_m / c.range_m, 0.05, 1.0), sources=np.full(n, SOURCE_RSU, dtype=np.int64))
    return out.take(observable & detected), delay_s


def _assert_same(got: ObjectArray, want: ObjectArray) -> None:
    for column in COLUMNS:
        a, b = getattr(got, column), getattr(want, column)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), column
        assert a.flags.writeable, column


@pytest.mark.parametrize("name", ["connected-intersection", "two-rsu-corridor", "dense-intersection"])
def test_detections_from_the_kept_rows_equal_the_take_of_every_row(name):
    scenario = load_scenario(name)
    site, kept = World(scenario, site=True), 0
    for v, spec in enumerate(scenario.vehicles):
        world = World(scenario, ego=spec.name)
        new, before = (Lidar(spec.lidar, np.random.default_rng(v)) for _ in range(2))
        for t_s in np.arange(0.0, scenario.duration_s, 0.7):
            got = new.detect(world, t_s)
            _assert_same(got, _lidar_before(before, world, t_s))
            kept += len(got)
    for r, cfg in enumerate(scenario.rsus):
        new, before = (RsuCamera(cfg, np.random.default_rng(10 + r)) for _ in range(2))
        for t_s in np.arange(0.0, scenario.duration_s, 0.7):
            (got, delay), (want, want_delay) = new.detect(site, t_s), _camera_before(before, site, t_s)
            _assert_same(got, want)
            assert delay == want_delay
            kept += len(got)
    assert kept > 100


def test_diagonal_covariances_are_fresh_tiles():
    for variance in (0.0, 0.01, 0.09, 2.5):
        for n in (0, 1, 5, 64, 65, 300, 3):
            got = _diagonal_covariances(variance, n)
            want = np.tile(np.eye(2) * variance, (n, 1, 1))
            assert got.tobytes() == want.tobytes() and got.shape == want.shape
            got[:] = -1.0  # a copy: the kept tile is untouched
            assert _diagonal_covariances(variance, n).tobytes() == want.tobytes()
