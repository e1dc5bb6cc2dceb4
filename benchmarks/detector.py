"""Image detector: speed per 640 x 384 frame and accuracy on held-out rendered frames.

    python benchmarks/detector.py [--model PATH] [--frames 300] [--runs 200] [--threads 2]

Speed: ``OnnxDetector.detect`` wall time (pre-processing + inference + post-processing) per
rendered 640 x 384 frame after 20 warm-up runs, p50 / p99 over ``--runs`` runs, on CPU with
``--threads`` intra-op threads (and on CUDA when onnxruntime has it), and the share of pre- and
post-processing. Accuracy: recall and precision at IoU >= 0.5 by range bin and class on
``--frames`` held-out frames (``tools/detector_dataset.py``, seed ``--seed``, never trained on:
training uses seed 0) and on the bundled scenarios' own RSU cameras (1 frame per second).
Ground truth: boxes with visible >= 0.3; less visible ones are ignored (a detection on one is
neither right nor wrong). A detection's range is its matched box's; an unmatched detection's is
where its bottom centre meets the ground (the camera's ground homography). Also the median
error of the box bottom edge (px) of matched boxes, which the RSU maps to the ground.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

from detector_dataset import SCENARIOS, render_frame  # noqa: E402
from v2i.perception.detector import OnnxDetector  # noqa: E402
from schemas.classes import ObjectClass  # noqa: E402
from v2i.sim.camera import PinholeCamera, rsu_camera  # noqa: E402
from v2i.sim.render import SceneRenderer  # noqa: E402
from v2i.sim.scenario import load_scenario  # noqa: E402
from v2i.sim.world import World  # noqa: E402

BINS_M = ((0.0, 50.0), (50.0, 80.0), (80.0, 120.0))
MIN_VISIBLE = 0.3
IOU_MATCH = 0.5


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU (N, M) of boxes a (N, 4) and b (M, 4), xyxy."""
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=2)
    area = lambda x: np.prod(np.clip(x[:, 2:] - x[:, :2], 0, None), axis=1)  # noqa: E731
    return inter / np.maximum(area(a)[:, None] + area(b)[None] - inter, 1e-9)


def ground_range_m(camera: PinholeCamera, xyxy: np.ndarray) -> np.ndarray:
    """Horizontal range (m) of where each box's bottom centre meets the ground (inf above the horizon)."""
    uv = camera.undistort(np.column_stack([(xyxy[:, 0] + xyxy[:, 2]) / 2, xyxy[:, 3]]))
    g = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(camera.ground_homography()).T  # [x, y, 1] ~ H^-1 [u, v, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = g[:, :2] / g[:, 2:]
        r = np.hypot(*(xy - camera.centre[:2]).T)
    return np.where(g[:, 2] * np.sign(np.linalg.det(camera.ground_homography())) > 0, r, np.inf)


def match_frame(dets, labels, camera: PinholeCamera, class_aware: bool) -> tuple[list, list]:
    """Greedy matching by score. GT rows (range, cls, matched, bottom err px); det rows (range, cls, tp)."""
    good = labels.visible >= MIN_VISIBLE
    gt_xyxy, gt_cls, gt_r = labels.xyxy[good], labels.cls[good], labels.range_m[good]
    iou = iou_matrix(dets.xyxy, gt_xyxy)
    iou_ignored = iou_matrix(dets.xyxy, labels.xyxy[~good])
    taken = np.zeros(len(gt_xyxy), bool)
    err = np.full(len(gt_xyxy), np.nan)
    det_rows = []
    det_range = ground_range_m(camera, dets.xyxy) if len(dets) else np.zeros(0)
    for i in np.argsort(-dets.scores):
        cand = iou[i] * (~taken) * ((gt_cls == dets.cls[i]) if class_aware else 1.0)
        j = int(np.argmax(cand)) if len(cand) else -1
        if j >= 0 and cand[j] >= IOU_MATCH:
            taken[j] = True
            err[j] = abs(dets.xyxy[i, 3] - gt_xyxy[j, 3])
            det_rows.append((gt_r[j], dets.cls[i], True))
        elif iou_ignored.shape[1] and iou_ignored[i].max() >= IOU_MATCH:
            continue  # on a box too occluded to count: neither right nor wrong
        else:  # on nothing, a duplicate or the wrong class: a false positive
            near = len(cand) and iou[i].max() >= IOU_MATCH
            det_rows.append((gt_r[int(np.argmax(iou[i]))] if near else det_range[i], dets.cls[i], False))
    gt_rows = [(gt_r[j], gt_cls[j], taken[j], err[j]) for j in range(len(gt_xyxy))]
    return gt_rows, det_rows


def held_out_frames(seed: int, count: int) -> list:
    """(image, labels, camera) of frames 0..count-1 of ``seed`` (random cameras and bodies)."""
    out = []
    for k in range(count):
        image, labels, info = render_frame(seed, k)
        out.append((image, labels, info["camera"]))
    return out


def rsu_frames(step_s: float = 1.0) -> list:
    """(image, labels, camera) of each pinned scenario's own RSU image camera every ``step_s``."""
    out = []
    for name in SCENARIOS:
        world = World(load_scenario(name))
        renderer, camera = SceneRenderer(world, seed=0), rsu_camera(world.scenario.rsu)
        rng = np.random.default_rng(7)
        for t in np.arange(0.0, world.duration_s, step_s):
            frame = renderer.render(camera, float(t), rng)
            out.append((frame.image, frame.labels, camera))
    return out


def speed(detector: OnnxDetector, images: list, runs: int) -> str:
    for image in images[:20]:
        detector.detect(image)
    total, parts = [], []
    for k in range(runs):
        detector.detect(images[k % len(images)])
        total.append(detector.last_ms)
        parts.append(detector.last_breakdown_ms)
    pre, infer, post = np.sum(parts, axis=0) / np.sum(total) * 100
    return (f"p50 {np.percentile(total, 50):.1f} ms  p99 {np.percentile(total, 99):.1f} ms  "
            f"(pre-processing {pre:.0f} %, inference {infer:.0f} %, post-processing {post:.0f} %; {runs} runs)")


def accuracy_table(detector: OnnxDetector, frames: list, title: str) -> list[str]:
    """Lines: per range bin, all classes then each class present; class-aware and class-agnostic."""
    rows = {True: ([], []), False: ([], [])}
    for image, labels, camera in frames:
        dets = detector.detect(image)
        for aware in (True, False):
            g, d = match_frame(dets, labels, camera, aware)
            rows[aware][0].extend(g), rows[aware][1].extend(d)
    lines = [title, f"  {'range':<10}{'class':<12}{'GT':>6}{'recall':>8}{'dets':>7}{'precision':>10}"
                    f"{'bottom err px p50':>19}{'   class-agnostic R / P':>24}"]
    for lo, hi in BINS_M:
        for cls in [None] + [c for c in ObjectClass if c != ObjectClass.UNKNOWN]:
            cells = []
            for aware in (True, False):
                g = [r for r in rows[aware][0] if lo <= r[0] < hi and (cls is None or r[1] == cls)]
                d = [r for r in rows[aware][1] if lo <= r[0] < hi and (cls is None or r[1] == cls)]
                cells.append((g, d))
            (g, d), (ga, da) = cells
            if not g and not d:
                continue
            rec = np.mean([r[2] for r in g]) if g else np.nan
            prec = np.mean([r[2] for r in d]) if d else np.nan
            err = np.nanmedian([r[3] for r in g]) if any(r[2] for r in g) else np.nan
            rec_a = np.mean([r[2] for r in ga]) if ga else np.nan
            prec_a = np.mean([r[2] for r in da]) if da else np.nan
            name = "all" if cls is None else cls.name.lower()
            lines.append(f"  {f'{lo:.0f}-{hi:.0f} m':<10}{name:<12}{len(g):>6}{rec:>8.3f}{len(d):>7}{prec:>10.3f}"
                         f"{err:>19.2f}{f'{rec_a:.3f} / {prec_a:.3f}':>24}")
    return lines


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=None, help="ONNX model (default: the shipped one)")
    ap.add_argument("--frames", type=int, default=300, help="held-out random frames for accuracy")
    ap.add_argument("--seed", type=int, default=1000, help="held-out frame seed (training uses 0)")
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--score", type=float, default=0.3)
    args = ap.parse_args(argv)
    import onnxruntime as ort

    cpu = OnnxDetector(args.model, providers=["CPUExecutionProvider"], threads=args.threads, score_threshold=args.score)
    size_mb = cpu.model_path.stat().st_size / 1e6
    print(f"model {cpu.model_path} ({size_mb:.2f} MB), input {cpu.input_wh[0]}x{cpu.input_wh[1]}, "
          f"score >= {args.score}, NMS IoU {cpu.nms_iou}, onnxruntime {ort.__version__}")
    frames = held_out_frames(args.seed, args.frames)
    images = [f[0] for f in frames]
    print(f"speed, CPU ({args.threads} threads), 640x384 rendered frames: {speed(cpu, images, args.runs)}")
    if "CUDAExecutionProvider" in ort.get_available_providers():
        gpu = OnnxDetector(args.model, providers=["CUDAExecutionProvider"], score_threshold=args.score)
        print(f"speed, CUDA: {speed(gpu, images, args.runs)}")
    else:
        print("speed, CUDA: not measured (onnxruntime has no CUDAExecutionProvider here)")
    head = f"IoU >= {IOU_MATCH}, ground truth visible >= {MIN_VISIBLE}"
    for line in accuracy_table(cpu, frames, f"accuracy on {len(frames)} held-out random frames (seed {args.seed}), {head}:"):
        print(line)
    rsu = rsu_frames()
    for line in accuracy_table(cpu, rsu, f"accuracy on {len(rsu)} frames of the scenarios' RSU cameras ({', '.join(SCENARIOS)}), {head}:"):
        print(line)


if __name__ == "__main__":
    main()
