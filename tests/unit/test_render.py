"""Renderer: labels against the camera model, occlusion, ego hiding, determinism, texture detail,
lane markings where the road network puts them, frustum clipping against shapely."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from shapely.geometry import Polygon, box

from v2i.core.objects import ObjectArray
from schemas.classes import ObjectClass
from v2i.sim import raster
from v2i.sim.camera import PinholeCamera, rsu_camera
from v2i.sim.maps.road_network import lane_bounds, road_network
from v2i.sim.render import SceneRenderer
from v2i.sim.scenario import Scenario, load_scenario
from v2i.sim.scene_faces import box_corners
from v2i.sim.world import World


def _body(name, xy_path, cls="car", size=(4.6, 1.85, 1.5), speed=0.0, yaw_deg=None):
    traj = {"path": [list(p) for p in xy_path], "speed": [[0.0, speed]]}
    if yaw_deg is not None:
        traj["yaw_deg"] = yaw_deg
    return {"name": name, "class": cls, "size": list(size), "trajectory": traj}


def _world(actors, buildings=(), ego_xy=(-20.0, -30.0)) -> World:
    """A small scenario without a road network (generic ground): fast to build."""
    return World(Scenario.model_validate({
        "name": "render-test", "duration_s": 10.0, "target": actors[0]["name"],
        "ego": _body("ego", [ego_xy], yaw_deg=90.0), "actors": list(actors), "buildings": list(buildings),
        "rsu": {"id": "rsu", "position": {"x": 0.0, "y": 0.0, "z": 6.0}, "yaw_deg": 0.0},
    }))


def _camera(x=0.0, y=0.0, z=3.0, yaw_deg=0.0, pitch_deg=5.0, **kw) -> PinholeCamera:
    return PinholeCamera.from_pose((x, y, z), np.deg2rad(yaw_deg), np.deg2rad(pitch_deg), **kw)


def _label(frame, body_id):
    k = np.flatnonzero(frame.labels.ids == body_id)
    return None if len(k) == 0 else {f: getattr(frame.labels, f)[k[0]] for f in ("cls", "xyxy", "visible", "range_m")}


@pytest.fixture(scope="module")
def rlr():
    world = World(load_scenario("red-light-runner"))
    return world, SceneRenderer(world, seed=0)


def test_label_is_the_projection_of_the_box_corners():
    world = _world([_body("car", [(20.0, 2.0)], yaw_deg=30.0)])
    cam = _camera()
    frame = SceneRenderer(world).render(cam, 0.0, hide_ego=True)
    lab = _label(frame, 1)
    corners = np.concatenate(list(box_corners((20.0, 2.0), 0.0, (4.6, 1.85, 1.5), np.deg2rad(30.0)).values()))
    uv, depth = cam.project(corners)
    assert np.all(depth > 0)
    expected = np.concatenate([uv.min(axis=0), uv.max(axis=0)])
    np.testing.assert_allclose(lab["xyxy"], expected, atol=1e-6)
    assert lab["cls"] == ObjectClass.CAR and lab["visible"] == pytest.approx(1.0)
    assert lab["range_m"] == pytest.approx(np.hypot(20.0, 2.0))


def test_distorted_label_follows_the_lens_and_the_image_is_remapped():
    world = _world([_body("car", [(15.0, -3.0)], yaw_deg=0.0)])
    ideal = _camera()
    cam = PinholeCamera(ideal.K, ideal.R, ideal.t, ideal.width, ideal.height, np.array([-0.3, 0.08, 0, 0, 0]))
    frame = SceneRenderer(world).render(cam, 0.0, hide_ego=True)
    corners = np.concatenate(list(box_corners((15.0, -3.0), 0.0, (4.6, 1.85, 1.5), 0.0).values()))
    uv, _ = cam.project(corners)
    lab = _label(frame, 1)
    # the lens bends the box's edges outward of its corners' box by at most a few pixels
    assert np.all(np.abs(lab["xyxy"] - np.concatenate([uv.min(axis=0), uv.max(axis=0)])) < 3.0)
    assert frame.image.shape == (384, 640, 3) and lab["visible"] == pytest.approx(1.0, abs=0.02)
    x0, y0, x1, y1 = np.round(lab["xyxy"]).astype(int)
    clean = SceneRenderer(world).render(ideal, 0.0, hide_ego=True).image
    assert not np.array_equal(frame.image, clean)
    assert frame.image[y0:y1, x0:x1].std() > 10  # the car is where the distorted label says


def test_actor_behind_a_building_is_hidden_then_reappears():
    building = {"name": "block", "box": {"x": 20.0, "y": 0.0, "l": 6.0, "w": 6.0}}
    world = _world([_body("car", [(35.0, -12.0), (35.0, 12.0)], speed=4.0)], [building])
    renderer, cam = SceneRenderer(world), _camera()
    hidden = _label(renderer.render(cam, 3.0, hide_ego=True), 1)  # at (35, 0): right behind the block
    assert hidden is not None and hidden["visible"] < 0.01
    out = _label(renderer.render(cam, 0.0, hide_ego=True), 1)  # at (35, -12): clear of it
    assert out["visible"] > 0.99


def test_nearer_actor_partly_hides_a_farther_one():
    world = _world([_body("far", [(30.0, 0.0)], yaw_deg=0.0), _body("near", [(15.0, 1.2)], yaw_deg=0.0)])
    frame = SceneRenderer(world).render(_camera(z=1.5, pitch_deg=0.0), 0.0, hide_ego=True)
    assert 0.05 < _label(frame, 1)["visible"] < 0.95
    assert _label(frame, 2)["visible"] == pytest.approx(1.0)


def test_bodies_out_of_view_are_not_listed():
    world = _world([_body("behind", [(-20.0, 0.0)]), _body("ahead", [(20.0, 0.0)])])
    frame = SceneRenderer(world).render(_camera(), 0.0, hide_ego=True)
    assert list(frame.labels.ids) == [2]


def test_ego_is_drawn_unless_hidden():
    world = _world([_body("car", [(40.0, 10.0)])], ego_xy=(20.0, 0.0))
    renderer, cam = SceneRenderer(world), _camera()
    shown, hidden = renderer.render(cam, 0.0), renderer.render(cam, 0.0, hide_ego=True)
    assert 0 in shown.labels.ids and 0 not in hidden.labels.ids
    x0, y0, x1, y1 = np.round(_label(shown, 0)["xyxy"]).astype(int)
    assert not np.array_equal(shown.image[y0:y1, x0:x1], hidden.image[y0:y1, x0:x1])


def test_clean_frames_are_deterministic_and_noisy_ones_depend_on_the_seed(rlr):
    world, renderer = rlr
    cam = rsu_camera(world.scenario.rsu)
    a, b = renderer.render(cam, 8.0), SceneRenderer(world, seed=0).render(cam, 8.0)
    assert np.array_equal(a.image, b.image)
    n1 = renderer.render(cam, 8.0, np.random.default_rng(1)).image
    n1_again = renderer.render(cam, 8.0, np.random.default_rng(1)).image
    n2 = renderer.render(cam, 8.0, np.random.default_rng(2)).image
    assert np.array_equal(n1, n1_again) and not np.array_equal(n1, n2) and not np.array_equal(n1, a.image)
    assert np.abs(n1.astype(int) - a.image).mean() < 25  # noise, not a different picture
    assert not np.array_equal(SceneRenderer(world, seed=1).render(cam, 8.0).image, a.image)


def test_orb_finds_features_on_a_near_car():
    world = _world([_body("car", [(9.0, 0.0)], yaw_deg=60.0)])
    frame = SceneRenderer(world).render(_camera(z=1.5, pitch_deg=0.0), 0.0, hide_ego=True)
    x0, y0, x1, y1 = _label(frame, 1)["xyxy"]
    keypoints = cv2.ORB_create(nfeatures=1000).detect(cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY), None)
    inside = [k for k in keypoints if x0 <= k.pt[0] <= x1 and y0 <= k.pt[1] <= y1]
    assert len(inside) >= 40


@pytest.mark.parametrize("cls", ["pedestrian", "cyclist", "motorcycle", "van", "truck", "bus", "unknown"])
def test_every_class_renders_and_is_labelled(cls):
    size = {"pedestrian": (0.6, 0.6, 1.75), "cyclist": (1.8, 0.6, 1.7), "motorcycle": (2.1, 0.8, 1.5),
            "truck": (8.0, 2.5, 3.5), "bus": (12.0, 2.55, 3.2)}.get(cls, (5.0, 2.0, 2.4))
    world = _world([_body("it", [(14.0, 0.0)], cls=cls, size=size, yaw_deg=45.0)])
    frame = SceneRenderer(world).render(_camera(width=320, height=200), 0.0, hide_ego=True)
    assert frame.image.shape == (200, 320, 3) and frame.image.dtype == np.uint8
    lab = _label(frame, 1)
    assert lab["cls"] == ObjectClass.parse(cls) and lab["visible"] == pytest.approx(1.0)


def test_render_bodies_draws_the_given_bodies(rlr):
    world, renderer = rlr
    cam = rsu_camera(world.scenario.rsu)
    bodies = ObjectArray(ids=np.array([7, 8]), cls=np.array([ObjectClass.PEDESTRIAN, ObjectClass.TRUCK]),
                         xy=np.array([[-20.0, -3.5], [-40.0, -1.75]]), z=np.array([0.875, 1.75]),
                         lwh=np.array([[0.6, 0.6, 1.75], [8.0, 2.5, 3.5]]), yaw=np.zeros(2), vxy=np.zeros((2, 2)))
    frame = renderer.render_bodies(cam, bodies)
    assert frame.t_s is None and set(frame.labels.ids) == {7, 8}
    assert set(frame.labels.cls) == {ObjectClass.PEDESTRIAN, ObjectClass.TRUCK}


def test_lane_markings_are_where_the_road_network_puts_them(rlr):
    world, renderer = rlr
    cam = rsu_camera(world.scenario.rsu)
    image = renderer.render(cam, 0.0).image.astype(float)
    net = road_network("red-light-runner")
    lane = next(ln for ln in net.lanes if ln.name == "eb-in-outer")
    start, end = lane_bounds(lane)[0][[0, -1]]  # its left line is dashed: 3 m on, 6 m off from its start
    along = (end - start) / np.linalg.norm(end - start)
    dash = start + along * (1.5 + 9.0 * np.floor((np.linalg.norm([-26.5, -3.5] - start) - 1.5) / 9.0))
    gap = dash + 4.5 * along

    def pixel(xy):
        (u, v), = cam.project(np.array([[xy[0], xy[1], 0.0]]))[0]
        return image[round(v), round(u)]

    asphalt = pixel(dash + np.array([0.0, 1.2]))
    assert pixel(dash).mean() > asphalt.mean() + 60  # white paint
    assert pixel(gap).mean() < asphalt.mean() + 25  # the gap between dashes is asphalt
    yellow = pixel((-30.0, 0.12))  # double yellow centre line, 0.12 m either side of y = 0
    assert yellow[2] > yellow[0] + 50 and yellow[1] > yellow[0] + 40  # R and G over B


def test_clip_polygon_matches_shapely():
    """Frustum clipping (Sutherland-Hodgman) against shapely on a polygon in the plane z = 2."""
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    planes = raster.frustum_planes(K, 100, 80)
    square = np.array([[-3.0, -3.0, 2.0], [3.0, -3.0, 2.0], [3.0, 3.0, 2.0], [-3.0, 3.0, 2.0]])
    clipped = raster.clip_polygon(square, planes)
    # at z = 2 the view spans u in [-m, W - 1 + m] -> x = (u - c_x) z / f
    m = raster.MARGIN_PX
    view = box((-m - 50) * 2 / 100, (-m - 40) * 2 / 100, (99 + m - 50) * 2 / 100, (79 + m - 40) * 2 / 100)
    expected = Polygon(square[:, :2]).intersection(view)
    assert Polygon(clipped[:, :2]).area == pytest.approx(expected.area, rel=1e-9)
    assert Polygon(clipped[:, :2]).symmetric_difference(expected).area < 1e-9
    behind = square - [0, 0, 4.0]  # z = -2: entirely behind the camera
    assert len(raster.clip_polygon(behind, planes)) == 0


def test_cli_writes_frames_labels_and_camera(tmp_path, capsys):
    import json

    from v2i.cli import main

    out = tmp_path / "frames"
    assert main(["camera", "render", "--scenario", "red-light-runner", "--out", str(out), "--start", "8",
                 "--duration", "0.4", "--clean", "--format", "png"]) == 0
    lines = [json.loads(s) for s in (out / "labels.jsonl").read_text().splitlines()]
    assert [ln["t_s"] for ln in lines] == pytest.approx([8.0, 8.2, 8.4])  # the RSU's 5 Hz
    assert all((out / ln["file"]).exists() for ln in lines)
    car = next(b for b in lines[0]["boxes"] if b["id"] == 1)
    assert car["class"] == "car" and car["visible"] == 1.0 and len(car["xyxy"]) == 4
    camera = json.loads((out / "camera.json").read_text())
    image = cv2.imread(str(out / lines[0]["file"]))
    assert image.shape == (camera["height"], camera["width"], 3) and np.asarray(camera["K"]).shape == (3, 3)
    (tmp_path / "file").write_text("")
    assert main(["camera", "render", "--out", str(tmp_path / "file"), "--duration", "0.2"]) == 2
    assert "--out" in capsys.readouterr().err


def test_turned_camera_matches_the_pose_angles_it_stands_for():
    cam = _camera(pitch_deg=11.0, yaw_deg=30.0)
    d, d_deg = 0.004, np.rad2deg(0.004)
    R = lambda c: c.R  # noqa: E731
    np.testing.assert_allclose(R(cam.turned(0.0, d, 0.0)), R(_camera(pitch_deg=11.0 + d_deg, yaw_deg=30.0)), atol=1e-12)
    np.testing.assert_allclose(R(cam.turned(0.0, 0.0, d)), R(_camera(pitch_deg=11.0, yaw_deg=30.0, roll_rad=d)), atol=1e-12)
    level = _camera(pitch_deg=0.0, yaw_deg=30.0)  # pan = yaw exactly when the axis is level
    np.testing.assert_allclose(R(level.turned(d, 0.0, 0.0)), R(_camera(pitch_deg=0.0, yaw_deg=30.0 + d_deg)), atol=1e-12)
    np.testing.assert_allclose(cam.turned(d, d, d).centre, cam.centre, atol=1e-12)  # about its own centre


def test_sway_is_stationary_with_its_sigma_and_a_function_of_time_only():
    from v2i.sim.camera import Sway

    sway = Sway.draw(0.1, 1.0, np.random.default_rng(3))
    t = np.arange(0.0, 600.0, 0.05)
    angles = np.rad2deg(np.array([sway.angles_rad(s) for s in t]))
    np.testing.assert_allclose(angles.std(axis=0), 0.1, rtol=0.25)
    assert np.abs(angles.mean(axis=0)).max() < 0.02
    np.testing.assert_array_equal(sway.angles_rad(7.3), Sway.draw(0.1, 1.0, np.random.default_rng(3)).angles_rad(7.3))
    cam = _camera()
    assert Sway.still().move(cam, 7.3) is cam


def test_pole_sway_moves_a_far_ground_point_as_r_squared_over_h():
    """dr = dpitch (r^2 + h^2) / h: the sway's range error grows with the square of the range."""
    h = 7.0
    cam = PinholeCamera.from_pose((0.0, 0.0, h), 0.0, np.deg2rad(8.0))
    tilted = cam.turned(0.0, np.deg2rad(0.1), 0.0)
    for r in (20.0, 70.0):
        uv, _ = tilted.project(np.array([[r, 0.0, 0.0]]))  # where the tilted camera sees the point ...
        hom = np.linalg.inv(cam.ground_homography()) @ np.append(uv[0], 1.0)  # ... read with the still calibration
        seen_r = hom[0] / hom[2]
        # tilted down, the camera sees the point higher in the image: it reads farther
        assert seen_r - r == pytest.approx(np.deg2rad(0.1) * (r ** 2 + h ** 2) / h, rel=0.05)


def test_rsu_view_sways_unless_clean(tmp_path):
    import json

    from v2i.cli import main

    def poses(*flags):
        out = tmp_path / "-".join(flags or ("noisy",))
        assert main(["camera", "render", "--scenario", "red-light-runner", "--out", str(out), "--start", "8",
                     "--duration", "0.4", "--format", "png", *flags]) == 0
        return [np.asarray(json.loads(s)["R"]) for s in (out / "labels.jsonl").read_text().splitlines()]

    clean, noisy = poses("--clean"), poses()
    np.testing.assert_array_equal(clean[0], clean[2])
    moved_deg = np.rad2deg(np.arccos(np.clip(np.einsum("ij,ij->i", noisy[0], noisy[2]), -1, 1)))
    assert 0.0 < moved_deg.max() < 1.5  # a fraction of a degree between frames
