"""Train the shipped image detector (``src/v2i/perception/models/v2i-det.onnx``) on rendered frames.

Two steps, each seeded and reproducible (same seed, same data, same thread count -> same model):

    # 1. render the training set (needs the v2i venv: v2i.sim.render)
    python tools/train_detector.py render --out /tmp/v2i-det-data --frames 3000 --seed 0
    # 2. train and export (needs torch: pip install -e '.[train]', or /work/train-venv)
    python tools/train_detector.py train --data /tmp/v2i-det-data --out src/v2i/perception/models/v2i-det.onnx

Model: a small plain-conv encoder (strides 2..32, ReLU, BatchNorm) with a top-down FPN back to
stride 4, and one anchor-free head at stride 4 (96 x 160 cells on a 384 x 640 input):
per cell, per-class heat logits and ltrb distances d = softplus(raw) * 4 px from the cell centre.
Training is CenterNet-like: a Gaussian heat target per box peaking (= 1) at the box centre's
cell, focal loss; ltrb regression (GIoU + size-normalised L1, bottom edge weighted double, since
the RSU puts the box's bottom centre on the ground) at the cells near the centre inside the box.
Boxes less than ``--min-visible`` visible (occluded) are ignored, not penalised: the heat loss
is masked inside them. The export decodes to the YOLOv8 layout [1, 4 + nc, A] (cx, cy, w, h in
input px, sigmoid scores) that ``v2i.perception.detector.OnnxDetector`` reads; NMS happens there.

Training: AdamW (lr 2e-3, warm-up then cosine), batches of 16 random 224 x 352 crops of the
rendered frames (scaled 0.5-1.5 x, flipped, colour-jittered; crops centred on rare classes more
often), the network in bfloat16 autocast (``--fp32`` to turn off). 12000 steps take about 30 min
on 2 CPU cores (AVX512-BF16). Code: ``tools/detector_dataset.py`` (scenes), ``tools/detector_samples.py``
(crops, targets), ``tools/detector_training.py`` (network, losses, export).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
CLASS_NAMES = ("car", "van", "truck", "bus", "pedestrian", "cyclist", "motorcycle")
STRIDE = 4
INPUT_HW = (384, 640)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="Run '<step> --help' for each step's options.")
    sub = p.add_subparsers(dest="step", required=True)
    r = sub.add_parser("render", help="render the training frames into a cache folder (v2i venv)")
    r.add_argument("--out", type=Path, default=Path("/tmp/v2i-det-data"))
    r.add_argument("--frames", type=int, default=3000)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--workers", type=int, default=1, help="processes rendering disjoint frame ranges")
    t = sub.add_parser("train", help="train on a rendered cache and export ONNX (torch)")
    t.add_argument("--data", type=Path, default=Path("/tmp/v2i-det-data"))
    t.add_argument("--out", type=Path, default=ROOT / "src/v2i/perception/models/v2i-det.onnx")
    t.add_argument("--steps", type=int, default=12000)
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--crop", type=int, nargs=2, default=(224, 352), metavar=("H", "W"))
    t.add_argument("--lr", type=float, default=2e-3)
    t.add_argument("--width", type=int, nargs=5, default=(16, 32, 48, 96, 128), metavar="C",
                   help="channels at strides 2, 4, 8, 16, 32")
    t.add_argument("--min-visible", type=float, default=0.3)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--fp32", dest="bf16", action="store_false",
                   help="train in float32 (default: bfloat16 autocast, ~2x faster on AVX512-BF16 CPUs)")
    t.add_argument("--log-every", type=int, default=100)
    t.add_argument("--checkpoint", type=Path, default=None, help="save/resume state here (.pt)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.step == "render":
        sys.path.insert(0, str(ROOT / "src"))
        sys.path.insert(0, str(ROOT / "tools"))
        from detector_dataset import render_dataset

        render_dataset(args.out, args.frames, args.seed, args.workers)
        return 0
    sys.path.insert(0, str(ROOT / "tools"))
    from detector_training import train

    train(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
