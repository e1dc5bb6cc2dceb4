"""The sensors' kept columns and short expressions against what they replace (v2i.sim.sensors), bit for bit."""

import numpy as np

from v2i.core.frames import Pose2D, base_to_map_points
from v2i.sim.scenario import load_scenario
from v2i.sim.sensors import Lidar, _confidence_clip


def test_confidence_clip_equals_np_clip():
    rng = np.random.default_rng(0)
    score = np.concatenate([rng.uniform(-2.0, 2.0, 4000), [0.05, 1.0, 0.0, -0.0, np.nan, np.inf, -np.inf,
                                                           np.nextafter(0.05, 0.0), np.nextafter(1.0, 2.0), 5e-324]])
    for part in (score, score[:0], score[:1]):
        assert _confidence_clip(part).tobytes() == np.clip(part, 0.05, 1.0).tobytes()


def test_lidar_origin_equals_the_mount_point_moved_to_map():
    spec = load_scenario("connected-intersection").vehicles[0]
    lidar = Lidar(spec.lidar, np.random.default_rng(0))
    rng = np.random.default_rng(1)
    for x, y, yaw in rng.uniform(-100.0, 100.0, (200, 3)):
        ego = Pose2D(x=x, y=y, yaw=yaw)
        want = base_to_map_points(np.array([[spec.lidar.mount.x, spec.lidar.mount.y]]), ego)[0]
        assert lidar.origin(ego).tobytes() == want.tobytes()
