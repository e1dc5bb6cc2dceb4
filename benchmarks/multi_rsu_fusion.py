"""Two RSU trackers fused in the OBU: Kalman update vs covariance intersection (RMSE, NEES).

Truth: ``--targets`` targets 1 km apart (association is never in doubt), each moving at
constant velocity with white acceleration noise (sigma ``--accel-std`` m/s^2, piecewise
constant over the 0.1 s step), for ``--duration`` s at 10 Hz. RSU A and RSU B each run their
own ``v2i.fusion.tracking.Tracker`` (CV) over their own noisy positions of the targets (std
``--std-a`` / ``--std-b`` m), so each RSU's estimates are correlated with its own past and
the two RSUs' errors share the targets' process noise. The OBU's Tracker gets, each cycle
t: predict(t); optionally its own LiDAR positions (std ``--std-lidar`` m, raw measurements,
source bit 0); RSU A's confirmed tracks (estimates, bit 1); RSU B's (estimates, bit 2 or,
in the "one bit" row, bit 1 as before issue 12); prune(t).

Rows (the OBU tracker's estimate fusion): ``RSU A alone`` (reference), ``one bit`` (both RSUs
as one source: the newest estimate replaces the state), ``kf`` (a source per RSU, plain Kalman
position update), ``ci`` (a source per RSU, covariance intersection of position and velocity
into tracks another RSU shares; the default), ``ci-all`` (CI also into tracks only the LiDAR
shares, which ``ci`` leaves to the Kalman update so that single-RSU runs are unchanged).
Metrics over OBU tracks after ``--burn-in-s``: position RMSE (m) against the truth, mean NEES
of the 2-D position e^T P^-1 e (2 for a consistent filter), share of NEES inside the 95 %
chi-square bound (5.99; 0.95 if consistent), and velocity RMSE (m/s).

    python benchmarks/multi_rsu_fusion.py [--seed 0] [--targets 50] [--duration 30] [--json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from v2i.core.objects import ObjectArray
from v2i.fusion.tracking import Tracker, TrackerConfig, slot_source
from schemas.messages import SOURCE_VEHICLE

STEP_S = 0.1
CHI2_2DOF_95 = 5.991
SPACING_M = 1000.0  # between targets: they drift by ~ sigma_a t^1.5 / sqrt(3), 95 m at 30 s for 1 m/s^2


def truth_paths(rng: np.random.Generator, n: int, steps: int, accel_std: float) -> np.ndarray:
    """(steps, n, 4) [x, y, vx, vy]: CV with white acceleration, targets SPACING_M apart in y."""
    state = np.zeros((steps, n, 4))
    state[0, :, 1] = SPACING_M * np.arange(n)
    state[0, :, 2:] = rng.normal(0.0, 8.0, (n, 2))
    for k in range(1, steps):
        a = rng.normal(0.0, accel_std, (n, 2))  # constant over the step: p += v dt + a dt^2 / 2
        state[k, :, :2] = state[k - 1, :, :2] + state[k - 1, :, 2:] * STEP_S + a * STEP_S**2 / 2
        state[k, :, 2:] = state[k - 1, :, 2:] + a * STEP_S
    return state


def positions(rng: np.random.Generator, truth: np.ndarray, std: float) -> ObjectArray:
    """Noisy position detections (n targets) with R = std^2 I and no velocity."""
    n = len(truth)
    return ObjectArray(ids=np.full(n, -1), cls=np.ones(n, int), xy=truth[:, :2] + rng.normal(0.0, std, (n, 2)),
                       z=np.zeros(n), lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=np.zeros(n), vxy=np.zeros((n, 2)),
                       cov_xy=np.tile(np.eye(2) * std**2, (n, 1, 1)))


def rsu_estimates(tracker: Tracker, dets: ObjectArray, t_s: float) -> ObjectArray:
    """One RSU cycle: its tracker's confirmed tracks after the detections of time t_s."""
    tracker.predict(t_s)
    tracker.update(dets, t_s)
    tracker.prune(t_s)
    return tracker.tracks(t_s)


def run(args: argparse.Namespace, variant: str, lidar: bool) -> dict:
    """Errors of the OBU's tracks for one variant (same seed, so the same truth and noise)."""
    rng = np.random.default_rng(args.seed)
    steps = round(args.duration / STEP_S) + 1
    truth = truth_paths(rng, args.targets, steps, args.accel_std)
    rsu_config = TrackerConfig(accel_std_mps2=args.accel_std)
    rsu_a, rsu_b = Tracker(rsu_config), Tracker(rsu_config)
    fusion = "kf" if variant == "kf" else "ci-all" if variant.endswith("ci-all") else "ci"
    obu = Tracker(TrackerConfig(accel_std_mps2=args.accel_std, estimate_fusion=fusion))
    bit_b = slot_source(0) if variant == "one bit" else slot_source(1)
    err, nees, verr = [], [], []
    for k in range(steps):
        t_s = k * STEP_S
        est_a = rsu_estimates(rsu_a, positions(rng, truth[k], args.std_a), t_s)
        est_b = rsu_estimates(rsu_b, positions(rng, truth[k], args.std_b), t_s)
        own = positions(rng, truth[k], args.std_lidar)
        obu.predict(t_s)
        if lidar:
            obu.update(own, t_s, SOURCE_VEHICLE)
        obu.update(est_a, t_s, slot_source(0), estimates=True)
        if not variant.startswith("RSU A alone"):
            obu.update(est_b, t_s, bit_b, estimates=True)
        obu.prune(t_s)
        out = obu.tracks(t_s)
        if t_s < args.burn_in_s or not len(out):
            continue
        gap = out.xy[:, None, :] - truth[k, None, :, :2]
        nearest = np.argmin((gap**2).sum(-1), axis=1)
        e = out.xy - truth[k, nearest, :2]
        err.append(e)
        nees.append(np.einsum("ki,kij,kj->k", e, np.linalg.inv(out.cov_xy), e))
        verr.append(out.vxy - truth[k, nearest, 2:])
    e, d2, ev = np.concatenate(err), np.concatenate(nees), np.concatenate(verr)
    return {"variant": variant, "lidar": lidar, "samples": len(e), "rmse_m": float(np.sqrt((e**2).sum(1).mean())),
            "nees_mean": float(d2.mean()), "nees_inside_95": float((d2 <= CHI2_2DOF_95).mean()),
            "velocity_rmse_mps": float(np.sqrt((ev**2).sum(1).mean()))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--targets", type=int, default=50)
    ap.add_argument("--duration", type=float, default=30.0, help="seconds at 10 Hz")
    ap.add_argument("--accel-std", type=float, default=1.0, help="truth white acceleration (m/s^2); filters use it")
    ap.add_argument("--std-a", type=float, default=0.8, help="RSU A position noise (m)")
    ap.add_argument("--std-b", type=float, default=1.0, help="RSU B position noise (m)")
    ap.add_argument("--std-lidar", type=float, default=0.5, help="own LiDAR position noise (m)")
    ap.add_argument("--burn-in-s", type=float, default=2.0)
    ap.add_argument("--json", action="store_true", help="print JSON rows instead of the table")
    args = ap.parse_args(argv)
    variants = ("RSU A alone", "one bit", "kf", "ci", "ci-all")
    rows = [run(args, v, lidar) for lidar in (False, True) for v in variants]
    rows.insert(6, run(args, "RSU A alone ci-all", True))
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"seed {args.seed}, {args.targets} targets x {args.duration:g} s at 10 Hz, sigma_a {args.accel_std} m/s^2, "
          f"RSU A {args.std_a} m, RSU B {args.std_b} m, LiDAR {args.std_lidar} m")
    print(f"{'OBU inputs':<14} {'fusion':<18} {'RMSE m':>8} {'NEES':>7} {'in 95%':>7} {'v RMSE':>7}")
    for r in rows:
        inputs = ("LiDAR + " if r["lidar"] else "") + ("A" if r["variant"].startswith("RSU A alone") else "A + B")
        print(f"{inputs:<14} {r['variant']:<18} {r['rmse_m']:8.3f} {r['nees_mean']:7.2f} {r['nees_inside_95']:7.3f} "
              f"{r['velocity_rmse_mps']:7.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
