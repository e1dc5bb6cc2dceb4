"""V2V offline (``v2i.offline.runner``): on connected-intersection, sharing what each vehicle's
own LiDAR sees gives the ego and car-2 the red-light runner earlier, through peer slots, with
each peer's clock learned over the V2V channels; nothing shared ever echoes back."""

import numpy as np
import pytest

from v2i.core.frames import Pose2D, base_to_map_points

from v2i.offline.runner import OfflineRun
from v2i.offline.spec import RunSpec
from schemas.codec import decode
from schemas.messages import SOURCE_VEHICLE, FusedObjectList

DURATION_S = 13.0  # car-3's LiDAR sees the runner from 4.5 s, the ego's from 10.0 s


@pytest.fixture(scope="module")
def runs() -> dict:
    out = {}
    for v2v in (False, True):
        run = OfflineRun(RunSpec(scenario="connected-intersection", seed=1, duration_s=DURATION_S, v2v=v2v))
        shared = []
        if v2v:
            deliver = run._peer_list

            def spy(sender, receiver, data, deliver=deliver):
                shared.append((sender.name, receiver.name, decode(data, FusedObjectList)))
                deliver(sender, receiver, data)

            run._peer_list = spy
        run.execute()
        out[v2v] = (run, run.report(), shared)
    return out


def test_v2v_gives_the_ego_and_car_2_the_runner_earlier(runs):
    off, on = runs[False][1]["vehicles"], runs[True][1]["vehicles"]
    for name in ("ego", "car-2"):
        assert on[name]["target"]["first_detection_distance_m"] > off[name]["target"]["first_detection_distance_m"] + 5.0
        assert on[name]["target"]["detected_cycles"] > off[name]["target"]["detected_cycles"]
        assert on[name]["target"]["id_switches"] == 0 and on[name]["output_deadline_miss_ratio"] == 0.0
    # car-3 sees it itself first: V2V changes little for it
    assert on["car-3"]["target"]["first_detection_distance_m"] == off["car-3"]["target"]["first_detection_distance_m"]
    assert runs[False][1]["v2v"] is None and runs[True][1]["v2v"]["link_profile"] == "lte-v2x"


def test_each_vehicle_hears_and_syncs_to_every_peer(runs):
    vehicles = runs[True][1]["vehicles"]
    for name, v in vehicles.items():
        assert sorted(v["peers"]) == sorted(set(vehicles) - {name})
        for peer, s in v["peers"].items():
            assert s["lists_accepted"] > 0.8 * DURATION_S * 10, (name, peer, s)
            assert s["slot"] >= 18  # after the 2 known + 16 unknown RSU slots
            # one true clock: the estimate is the error; it stays inside its bound, and is small
            assert abs(s["clock_offset_ms"]) <= s["clock_uncertainty_ms"] and abs(s["clock_offset_ms"]) < 2.0
        assert set(v["v2v_rejected"]) <= {"v2v_ego_self_detection"}  # peers see us: dropped, counted


def test_nothing_shared_echoes(runs):
    _, _, shared = runs[True]
    assert len(shared) > 6 * DURATION_S * 10 * 0.9
    for sender, receiver, msg in shared:
        assert sender != receiver and msg.vehicle_id == sender
        assert all(o.sources & SOURCE_VEHICLE for o in msg.objects)  # only the sender's own perception
    # the ego's LiDAR cannot see the runner before t = 10 s, while its fused output has it (from car-3
    # and the RSUs): none of what the ego shares before then lies on the runner
    run = runs[True][0]
    world = run.vehicles[0].world
    early = [m for s, _, m in shared if s == "ego" and m.cycle_time_ns < run.start_ns + 9_500_000_000]
    assert len(early) > 100
    near = 0
    for msg in early:
        actors = world.actors_at((msg.cycle_time_ns - run.start_ns) * 1e-9)
        truth = actors.xy[np.flatnonzero(actors.ids == world.target_id)[0]]
        xy = base_to_map_points(np.array([[o.x, o.y] for o in msg.objects]).reshape(-1, 2),
                                Pose2D(msg.ego_x, msg.ego_y, msg.ego_yaw))
        near += int(len(xy) > 0 and np.hypot(*(xy - truth).T).min() < 5.0)
    assert near == 0
    assert runs[True][1]["vehicles"]["ego"]["target"]["detected_cycles"] > 20  # it is in the ego's output
