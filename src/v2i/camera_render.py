"""``v2i camera render``: render a scenario's camera to image files with box labels.

Writes ``DIR/frame_00000.jpg`` (or .png), one per capture time, ``DIR/labels.jsonl`` (one line
per frame: file, t_s, boxes with id, class, xyxy px, visible fraction, range_m, and the
frame's camera pose R, t: the ego's moves, the RSU's sways in the wind) and ``DIR/camera.json``
(K, dist, R, t, width, height).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

VIEWS = ("rsu", "ego")
DESCRIPTION = """\
Render what a scenario's camera sees (v2i.sim.render) and write the frames with their ground-truth
boxes: for training and checking the detector, and for image-level fusion.

--view rsu: the RSU's physical camera (the scenario's rsu.image: yaw, pitch, fov, size,
distortion) on its pole, swaying in the wind (rsu.image.sway_deg, default 0.1 deg),
from rsu.phase_s at rsu.rate_hz. --view ego: the ego's
on-board camera (the scenario's ego_camera; a scenario without one gets the default
VehicleCameraConfig: 1.5 m ahead of the ego's centre, 1.4 m up, looking ahead, 90 deg, 640 x 384,
10 Hz), moving with the ego, which it does not see (hidden).

Labels list only bodies with a pixel in the image (the ego is id 0). xyxy: the box of the
projected 3-D box corners, clipped to the image; visible: the fraction of its silhouette not
hidden by nearer things. --noise (default) adds random exposure, blur and sensor noise from
--seed (the stream rsu_render / ego_render that v2i eval uses) and the pole's sway; --clean
renders noiseless, deterministic frames from a still pole. --seed also fixes the textures."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add ``render`` to the ``v2i camera`` subparsers object and return its parser."""
    p = subparsers.add_parser("render", help="render a scenario's RSU or ego camera to frames + box labels",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", default="red-light-runner", help="bundled scenario name or YAML path (default %(default)s)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for frames, labels.jsonl and camera.json")
    p.add_argument("--view", choices=VIEWS, default="rsu", help="which camera (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of textures and sensor noise (default %(default)s)")
    p.add_argument("--rate", type=float, metavar="HZ", help="frames per second (default: the camera's rate)")
    p.add_argument("--start", type=float, default=None, metavar="S",
                   help="first capture time, s (default: the RSU's phase_s, or 0 for the ego)")
    p.add_argument("--duration", type=float, metavar="S", help="seconds of scenario (default: all of it)")
    p.add_argument("--noise", dest="noise", action="store_true", default=True, help="sensor effects on (default)")
    p.add_argument("--clean", dest="noise", action="store_false", help="no sensor effects: deterministic frames")
    p.add_argument("--format", choices=("jpg", "png"), default="jpg", help="image format (default %(default)s)")
    p.set_defaults(func=run)
    return p


def _check(args) -> None:
    for name in ("rate", "duration"):
        value = getattr(args, name)
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ValueError(f"--{name} must be a finite number > 0, got {value}")
    if args.start is not None and not (np.isfinite(args.start) and args.start >= 0):
        raise ValueError(f"--start must be a finite number >= 0, got {args.start}")


def _camera_setup(world, view: str, sway_rng):
    """(camera at time t function, rate_hz, first capture time, noise stream name, hide_ego);
    the RSU's pole sways when ``sway_rng`` (numpy Generator) is given."""
    from v2i.sim.camera import Sway, rsu_camera, rsu_sway, vehicle_camera
    from v2i.sim.scenario import VehicleCameraConfig

    sc = world.scenario
    if view == "rsu":
        cam = rsu_camera(sc.rsu)
        sway = rsu_sway(sc.rsu, sway_rng) if sway_rng is not None else Sway.still()
        return (lambda t_s: sway.move(cam, t_s)), sc.rsu.rate_hz, sc.rsu.phase_s, "rsu_render", False
    cfg = sc.ego_camera or VehicleCameraConfig()
    return (lambda t_s: vehicle_camera(cfg, world.ego_at(t_s))), cfg.rate_hz, 0.0, "ego_render", True


def _prepare_out(out: str) -> Path:
    folder = Path(out)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    probe = folder / ".v2i-write-test"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise OSError(f"--out {out}: cannot write there ({exc.strerror or exc})") from None
    return folder


def _camera_json(camera, view: str, rate_hz: float, args) -> dict:
    return {"scenario": args.scenario, "view": view, "width": camera.width, "height": camera.height,
            "K": camera.K.tolist(), "dist": camera.dist.tolist(), "R": camera.R.tolist(), "t": camera.t.tolist(),
            "rate_hz": rate_hz, "seed": args.seed, "noise": args.noise,
            "note": "X_c = R X_w + t (map: x east, y north, z up; camera: x right, y down, z forward); "
                    "R, t are the first frame's, each labels line has its own"}


def _label_line(name: str, t_s: float, labels, camera) -> dict:
    from schemas.classes import ObjectClass

    boxes = [{"id": int(i), "class": ObjectClass(int(c)).name.lower(), "xyxy": [round(float(v), 2) for v in box],
              "visible": round(float(vis), 4), "range_m": round(float(r), 3)}
             for i, c, box, vis, r in zip(labels.ids, labels.cls, labels.xyxy, labels.visible, labels.range_m)]
    return {"file": name, "t_s": round(t_s, 6), "boxes": boxes, "R": camera.R.tolist(), "t": camera.t.tolist()}


def run(args: argparse.Namespace) -> int:
    import cv2

    from v2i.sim.render import SceneRenderer
    from v2i.sim.scenario import load_scenario
    from v2i.sim.seeding import stream
    from v2i.sim.world import World

    _check(args)
    world = World(load_scenario(args.scenario))
    sway_rng = stream(args.seed, "rsu_sway") if args.noise else None
    camera_at, rate_hz, phase_s, stream_name, hide_ego = _camera_setup(world, args.view, sway_rng)
    rate_hz = args.rate or rate_hz
    start_s = phase_s if args.start is None else args.start
    end_s = start_s + args.duration if args.duration is not None else world.duration_s
    times = start_s + np.arange(int(np.floor((end_s - start_s) * rate_hz + 1e-9)) + 1) / rate_hz
    times = times[times <= min(end_s, world.duration_s) + 1e-9]
    if len(times) == 0:
        raise ValueError(f"no capture time in [{start_s:g}, {end_s:g}] s (scenario lasts {world.duration_s:g} s)")
    folder = _prepare_out(args.out)
    renderer = SceneRenderer(world, args.seed)
    rng = stream(args.seed, stream_name) if args.noise else None
    (folder / "camera.json").write_text(json.dumps(_camera_json(camera_at(times[0]), args.view, rate_hz, args), indent=2))
    tty, spent_s = sys.stderr.isatty(), 0.0
    with open(folder / "labels.jsonl", "w") as labels_file:
        for k, t_s in enumerate(times):
            camera = camera_at(float(t_s))
            t0 = time.perf_counter()
            frame = renderer.render(camera, float(t_s), rng, hide_ego=hide_ego)
            spent_s += time.perf_counter() - t0
            name = f"frame_{k:05d}.{args.format}"
            if not cv2.imwrite(str(folder / name), frame.image):
                raise OSError(f"--out {args.out}: could not write {name}")
            labels_file.write(json.dumps(_label_line(name, float(t_s), frame.labels, camera)) + "\n")
            if tty or (k + 1) % 25 == 0 or k + 1 == len(times):
                end = "\r" if tty and k + 1 < len(times) else "\n"
                print(f"frame {k + 1}/{len(times)}  t = {t_s:.2f} s  {1e3 * spent_s / (k + 1):.1f} ms/frame rendering",
                      end=end, file=sys.stderr, flush=True)
    print(f"wrote {len(times)} frames, labels.jsonl and camera.json to {folder}")
    return 0
