"""Torch side of ``tools/train_detector.py``: network, targets, losses, training loop, ONNX export.

Only the training tool imports this (torch is an optional ``train`` extra, never a runtime need).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from detector_samples import CLASS_NAMES, INPUT_HW, STRIDE, CropSampler, load_cache

NC = len(CLASS_NAMES)
HEAT_PRIOR = 0.01  # initial class probability: bias = -log((1 - p) / p)


def cbr(c_in: int, c_out: int, stride: int = 1, k: int = 3) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, k, stride, k // 2, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class DetectorNet(nn.Module):
    """Input (B, 3, H, W) RGB in [0, 1], H, W multiples of 32 -> raw map (B, 4 + nc, H/4, W/4):
    channels 0..3 ltrb logits, 4.. class heat logits."""

    def __init__(self, widths=(16, 32, 48, 96, 128), nc: int = NC):
        super().__init__()
        c2, c4, c8, c16, c32 = widths
        self.s4 = nn.Sequential(cbr(3, c2, 2), cbr(c2, c4, 2), cbr(c4, c4))
        self.s8 = nn.Sequential(cbr(c4, c8, 2), cbr(c8, c8), cbr(c8, c8))
        self.s16 = nn.Sequential(cbr(c8, c16, 2), cbr(c16, c16), cbr(c16, c16))
        self.s32 = nn.Sequential(cbr(c16, c32, 2), cbr(c32, c32), cbr(c32, c32))
        self.lat32, self.fuse16 = cbr(c32, c16, k=1), cbr(c16, c16)
        self.lat16, self.fuse8 = cbr(c16, c8, k=1), cbr(c8, c8)
        self.lat8, self.fuse4 = cbr(c8, c4, k=1), cbr(c4, c4)
        head = c4 * 3 // 2
        self.head = nn.Sequential(cbr(c4, head), nn.Conv2d(head, 4 + nc, 1))
        nn.init.constant_(self.head[-1].bias[4:], -math.log((1 - HEAT_PRIOR) / HEAT_PRIOR))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x4 = self.s4(x)
        x8 = self.s8(x4)
        x16 = self.s16(x8)
        x32 = self.s32(x16)
        up = lambda t: F.interpolate(t, scale_factor=2.0, mode="nearest")  # noqa: E731
        y16 = self.fuse16(x16 + up(self.lat32(x32)))
        y8 = self.fuse8(x8 + up(self.lat16(y16)))
        y4 = self.fuse4(x4 + up(self.lat8(y8)))
        return self.head(y4)


def decode_ltrb(raw: torch.Tensor) -> torch.Tensor:
    """ltrb distances (px) from raw logits: d = softplus(raw) * stride."""
    return F.softplus(raw) * STRIDE


class YoloV8Export(nn.Module):
    """(1, 3, H, W) -> (1, 4 + nc, A): cx, cy, w, h (input px), sigmoid scores; A = (H/4) (W/4) row-major."""

    def __init__(self, net: DetectorNet, input_hw=INPUT_HW):
        super().__init__()
        self.net = net
        h, w = input_hw[0] // STRIDE, input_hw[1] // STRIDE
        gy, gx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        centres = torch.stack([gx, gy]).reshape(1, 2, h * w).float().add(0.5).mul(STRIDE)  # cell centres (px)
        self.register_buffer("centres", centres)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.net(x).flatten(2)
        d = decode_ltrb(out[:, :4])
        lt, rb = d[:, :2], d[:, 2:]
        cxcy = self.centres + (rb - lt) / 2  # (x0 + x1) / 2 with x0 = c - l, x1 = c + r
        return torch.cat([cxcy, lt + rb, out[:, 4:].sigmoid()], dim=1)


def heat_loss(logits: torch.Tensor, heat: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """CenterNet focal loss: pos -(1-p)^2 log p at heat == 1, neg -(1-y)^4 p^2 log(1-p); / n_pos."""
    p = logits.sigmoid().clamp(1e-4, 1 - 1e-4)
    pos = heat.ge(0.999).float()
    pos_loss = -(1 - p).pow(2) * F.logsigmoid(logits) * pos
    neg_loss = -(1 - heat).pow(4) * p.pow(2) * F.logsigmoid(-logits) * (1 - pos) * weight
    return (pos_loss.sum() + neg_loss.sum()) / pos.sum().clamp(min=1.0)


def box_loss(raw_ltrb: torch.Tensor, reg: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """GIoU and size-normalised L1 of ltrb at the regression cells; bottom edge counts double."""
    if len(reg["b"]) == 0:
        z = raw_ltrb.sum() * 0.0
        return z, z
    pred = decode_ltrb(raw_ltrb[reg["b"], :, reg["y"], reg["x"]])  # (K, 4)
    gt, w = reg["ltrb"], reg["w"]
    area_p = (pred[:, 0] + pred[:, 2]) * (pred[:, 1] + pred[:, 3])
    area_g = (gt[:, 0] + gt[:, 2]) * (gt[:, 1] + gt[:, 3])
    inter = (torch.min(pred[:, 0], gt[:, 0]) + torch.min(pred[:, 2], gt[:, 2])) * \
            (torch.min(pred[:, 1], gt[:, 1]) + torch.min(pred[:, 3], gt[:, 3]))
    hull = (torch.max(pred[:, 0], gt[:, 0]) + torch.max(pred[:, 2], gt[:, 2])) * \
           (torch.max(pred[:, 1], gt[:, 1]) + torch.max(pred[:, 3], gt[:, 3]))
    union = area_p + area_g - inter
    giou = inter / union - (hull - union) / hull  # both boxes contain the cell centre: inter > 0
    size = torch.stack([gt[:, 0] + gt[:, 2], gt[:, 1] + gt[:, 3]] * 2, dim=1).clamp(min=STRIDE)
    l1 = ((pred - gt).abs() / size * torch.tensor([1.0, 1.0, 1.0, 2.0])).sum(1)
    return ((1 - giou) * w).sum() / w.sum(), (l1 * w).sum() / w.sum()


def learning_rate(step: int, steps: int, base: float, warmup: int = 200) -> float:
    """Linear warm-up, then cosine decay to 2 % of ``base``."""
    if step < warmup:
        return base * (step + 1) / warmup
    progress = (step - warmup) / max(1, steps - warmup)
    return base * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * progress)))


def as_torch(batch: dict) -> dict:
    reg = {k: torch.from_numpy(v) for k, v in batch["reg"].items()}
    return {"images": torch.from_numpy(batch["images"]), "heat": torch.from_numpy(batch["heat"]),
            "weight": torch.from_numpy(batch["weight"]), "reg": reg}


def step_loss(model: nn.Module, batch: dict, bf16: bool) -> tuple[torch.Tensor, tuple[float, float, float]]:
    """loss = heat focal + 2 GIoU + L1 (size-normalised); the network in bfloat16 autocast if ``bf16``."""
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        out = model(batch["images"])
    out = out.float()
    lh = heat_loss(out[:, 4:], batch["heat"], batch["weight"])
    lg, l1 = box_loss(out[:, :4], batch["reg"])
    return lh + 2.0 * lg + l1, (lh.item(), lg.item(), l1.item())


def train(args) -> None:
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    sampler = CropSampler(load_cache(args.data), args.crop, args.min_visible)
    model = DetectorNet(tuple(args.width))
    decay = [p for n, p in model.named_parameters() if p.ndim > 1]
    rest = [p for n, p in model.named_parameters() if p.ndim <= 1]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": 5e-4}, {"params": rest, "weight_decay": 0.0}], lr=args.lr)
    start = 0
    if args.checkpoint is not None and args.checkpoint.is_file():
        state = torch.load(args.checkpoint, weights_only=False)
        model.load_state_dict(state["model"]), opt.load_state_dict(state["opt"])
        rng.bit_generator.state, start = state["rng"], state["step"]
        torch.set_rng_state(state["torch_rng"])
        print(f"resumed at step {start}", flush=True)
    model.train()
    t0, seen, sums = time.perf_counter(), 0, np.zeros(3)
    for step in range(start, args.steps):
        for group in opt.param_groups:
            group["lr"] = learning_rate(step, args.steps, args.lr)
        loss, parts = step_loss(model, as_torch(sampler.batch(rng, args.batch)), args.bf16)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        sums += parts
        seen += args.batch
        if (step + 1) % args.log_every == 0:
            dt = time.perf_counter() - t0
            print(f"step {step + 1}/{args.steps}  heat {sums[0] / args.log_every:.3f}  giou {sums[1] / args.log_every:.3f}"
                  f"  l1 {sums[2] / args.log_every:.3f}  lr {opt.param_groups[0]['lr']:.2e}  {seen / dt:.1f} crops/s"
                  f"  {dt:.0f} s", flush=True)
            sums[:] = 0
        if args.checkpoint is not None and (step + 1) % 500 == 0:
            torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "rng": rng.bit_generator.state,
                        "step": step + 1, "torch_rng": torch.get_rng_state()}, args.checkpoint)
    print(f"trained {args.steps - start} steps in {time.perf_counter() - t0:.0f} s", flush=True)
    export(model, args.out, vars(args))


def export(model: DetectorNet, out: Path, train_args: dict) -> None:
    """ONNX (opset 17), YOLOv8 layout, ultralytics-style metadata (names, stride, imgsz) + layout."""
    import onnx

    model.eval()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(1, 3, *INPUT_HW)
    torch.onnx.export(YoloV8Export(model), dummy, str(out), input_names=["images"], output_names=["output0"],
                      opset_version=17, dynamo=False)
    proto = onnx.load(str(out))
    meta = {
        "names": str({i: n for i, n in enumerate(CLASS_NAMES)}), "stride": str(STRIDE), "layout": "yolov8",
        "imgsz": str(list(INPUT_HW)), "task": "detect", "author": "v2i tools/train_detector.py",
        "description": "v2i rendered-frame detector, stride-4 anchor-free head, YOLOv8 output layout",
        "training": json.dumps({k: (str(v) if isinstance(v, Path) else v) for k, v in train_args.items()
                                if k not in ("checkpoint",)}),
    }
    del proto.metadata_props[:]
    for k, v in meta.items():
        proto.metadata_props.add(key=k, value=v)
    onnx.save(proto, str(out))
    print(f"exported {out} ({out.stat().st_size / 1e6:.2f} MB)", flush=True)
