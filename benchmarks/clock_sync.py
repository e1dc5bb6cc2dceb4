"""Clock sync over the link emulator's channel models: accuracy, step recovery, honesty of the bound.

Per seed: 10 Hz time exchanges through a link profile's uplink and downlink channels (the
downlink also carries ``--extra-down`` other messages per reply, as RSU object and prediction
lists share it in ``v2i eval``, so the jitter's message-to-message correlation is the eval's),
against an RSU clock with an offset, a drift and optionally one step. The estimate is scored
every 100 ms (the eval's cycle) against the truth:

- recovery: seconds after the step until |error| < 1 ms for good (as ``clock_step_recovery_s``),
  and the same for an oracle that knows the drift and each exchange's true one-way delays and
  takes the lower-tail means (q = 0.1) of the exchanges sent after the step: its error
  (lowmean(up) - lowmean(down)) / 2 is what the post-step delays themselves allow;
- p95 |error| from 5 s on, outside the 3 s after the step (as ``clock_offset_error_ms``);
- unbounded: share of scored times where |error| > the stated uncertainty;
- drift: the drift estimate's error (ppm, estimate - truth) at 5, 10, 20 and 30 s (the last
  scored time at or before each), and ``drift_converged_s``, the time until |drift error| stays
  below 5 ppm to the end of the run (null: not below at the end); the summary gives their
  medians and p95 over seeds (|error|; p95 and the convergence time as order statistics,
  a run that never converged counting as infinite).

    python benchmarks/clock_sync.py [--profile iaad-field] [--seeds 1-50] [--step-ms 500] [--json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from link_emulator.channel import Channel, LinkModel
from link_emulator.profile import load_profile
from v2i.clock.clock_sync import NS_PER_S, ClockSync, OffsetEstimate
from v2i.sim.sync_sim import exchanges, run_sync
from v2i.sim.clock import ClockStep, DriftingClock, SimClock

T0 = 1_767_225_600 * NS_PER_S
NS_PER_MS = 1_000_000
GRID_NS = 100 * NS_PER_MS
DRIFT_AT_S = (5, 10, 20, 30)  # when the drift error is reported
DRIFT_TOL_PPM = 5.0  # converged: |drift error| below this for good


class DriftRecorder(ClockSync):
    """A ClockSync that keeps the drift (ppm) of every estimate_at answer by the time asked
    (run_sync asks once per grid time, after the exchanges that arrived by then)."""

    def __init__(self) -> None:
        super().__init__()
        self.drift_ppm_at: dict[int, float] = {}

    def estimate_at(self, t_obu_ns: int) -> OffsetEstimate | None:
        est = super().estimate_at(t_obu_ns)
        if est is not None:
            self.drift_ppm_at[t_obu_ns] = est.drift_ppm
        return est


def drift_figures(t_ns: np.ndarray, drift_err_ppm: np.ndarray) -> dict:
    """drift_err_ppm (m,) on the grid t_ns (ns since start): the error at each DRIFT_AT_S and the
    time until |error| < DRIFT_TOL_PPM for good (None when it is not at the end)."""
    out = {}
    for at_s in DRIFT_AT_S:
        before = np.flatnonzero(t_ns <= at_s * NS_PER_S)
        out[f"drift_err_{at_s}s_ppm"] = None if not len(before) else round(float(drift_err_ppm[before[-1]]), 1)
    bad = np.abs(drift_err_ppm) >= DRIFT_TOL_PPM
    converged = 0.0 if not bad.any() else None if bad[-1] else (t_ns[bad][-1] + GRID_NS) / NS_PER_S
    out["drift_converged_s"] = None if converged is None else round(float(converged), 2)
    return out


def order_stat(values: list, p: float) -> float | None:
    """The p-quantile as an order statistic (numpy's "higher"), None counted as infinite; None if infinite."""
    x = np.array([np.inf if v is None else abs(v) for v in values], dtype=float)
    q = float(np.percentile(x, p, method="higher"))
    return None if np.isinf(q) else round(q, 2)


def channel_draw(channel: Channel, extra_messages: int, period_ns: int):
    """A sync_sim leg over a channel: ``extra_messages`` other messages go first, evenly spaced in
    the period before the exchange's own (they only advance the channel's correlated state)."""
    def draw(send_ns: int, rng: np.random.Generator) -> int | None:
        for k in range(extra_messages, 0, -1):
            channel.transmit(send_ns - k * period_ns // (extra_messages + 1), 1000)
        arrival = channel.transmit(send_ns, 200)
        return None if arrival is None else arrival - send_ns
    return draw


def one_seed(args, seed: int) -> dict:
    step_at_ns = T0 + round(args.step_at_s * NS_PER_S)
    steps = (ClockStep(step_at_ns, round(args.step_ms * NS_PER_MS)),) if args.step_ms else ()
    clock = DriftingClock(SimClock(), round(args.offset_ms * NS_PER_MS), args.drift_ppm, T0, steps)
    link = LinkModel(load_profile(args.profile), seed)
    period_ns = NS_PER_S // 10
    samples = exchanges(clock, channel_draw(link.uplink, 0, period_ns),
                        channel_draw(link.downlink, args.extra_down, period_ns), np.random.default_rng(seed),
                        T0, round(args.duration_s * NS_PER_S))
    sync = DriftRecorder()
    run = run_sync(clock, samples, T0, round(args.duration_s * NS_PER_S), sync=sync, grid_ns=GRID_NS)
    drift_err_ppm = np.array([sync.drift_ppm_at[T0 + t] for t in run.t_ns]) - args.drift_ppm
    scored = run.t_ns >= 5 * NS_PER_S
    rel_step_ns = step_at_ns - T0
    if steps:
        scored &= ~((run.t_ns >= rel_step_ns) & (run.t_ns < rel_step_ns + 3 * NS_PER_S))
    err_ms = np.abs(run.error_ns[scored]) / NS_PER_MS
    out = {"seed": seed, "p95_ms": round(float(np.percentile(err_ms, 95)), 3),
           "max_ms": round(float(err_ms.max()), 3),
           "unbounded": round(float(np.mean(np.abs(run.error_ns[scored]) > run.uncertainty_ns[scored])), 4),
           "uncertainty_p50_ms": round(float(np.median(run.uncertainty_ns[scored])) / NS_PER_MS, 2),
           "steps": run.steps_detected, **drift_figures(run.t_ns, drift_err_ppm)}
    if steps:
        out["recovery_s"] = round(run.reconvergence_ns(rel_step_ns) / NS_PER_S, 2)
        out["oracle_recovery_s"] = oracle_recovery_s(clock, samples, step_at_ns, round(args.duration_s * NS_PER_S))
    return out


def oracle_recovery_s(clock: DriftingClock, samples, step_at_ns: int, duration_ns: int, q: float = 0.1) -> float:
    """Recovery of the oracle described in the module doc, on the same grid."""
    after = [s for s in samples if s.t1_ns >= step_at_ns]
    up = np.array([s.t2_ns - clock.offset_at(s.t1_ns) - s.t1_ns for s in after], dtype=float)
    down = np.array([s.t4_ns - s.t3_ns + clock.offset_at(s.t4_ns) for s in after], dtype=float)
    t4 = np.array([s.t4_ns for s in after])
    last_bad_ns = step_at_ns
    for t in range(step_at_ns, T0 + duration_ns, GRID_NS):
        arrived = t4 <= t
        if not arrived.any():
            last_bad_ns = t
            continue
        k = max(1, int(np.ceil(q * arrived.sum())))
        err = 0.5 * (np.sort(up[arrived])[:k].mean() - np.sort(down[arrived])[:k].mean())
        if abs(err) >= NS_PER_MS:
            last_bad_ns = t
    return round((last_bad_ns + GRID_NS - step_at_ns) / NS_PER_S, 2)


def seeds(text: str) -> list[int]:
    low, _, high = text.partition("-")
    return list(range(int(low), int(high or low) + 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profile", default="iaad-field")
    parser.add_argument("--seeds", type=seeds, default=seeds("1-50"), help="e.g. 1-50")
    parser.add_argument("--offset-ms", type=float, default=350.0)
    parser.add_argument("--drift-ppm", type=float, default=60.0)
    parser.add_argument("--step-ms", type=float, default=500.0)
    parser.add_argument("--step-at-s", type=float, default=15.0)
    parser.add_argument("--duration-s", type=float, default=30.0)
    parser.add_argument("--extra-down", type=int, default=2, help="other downlink messages per reply")
    parser.add_argument("--json", action="store_true", help="one JSON object per seed, then the summary")
    args = parser.parse_args()
    rows = [one_seed(args, seed) for seed in args.seeds]
    p95 = np.array([r["p95_ms"] for r in rows])
    summary = {"profile": args.profile, "seeds": len(rows), "p95_ms_median": round(float(np.median(p95)), 3),
               "unbounded_max": max(r["unbounded"] for r in rows),
               "false_steps": sum(r["steps"] != (1 if args.step_ms else 0) for r in rows)}
    for at_s in DRIFT_AT_S:
        errs = [r[f"drift_err_{at_s}s_ppm"] for r in rows if r[f"drift_err_{at_s}s_ppm"] is not None]
        if errs:
            summary[f"drift_err_{at_s}s_ppm_p50"] = round(float(np.median(np.abs(errs))), 1)
            summary[f"drift_err_{at_s}s_ppm_p95"] = order_stat(errs, 95)
    converged = [r["drift_converged_s"] for r in rows]
    summary.update({"drift_converged_s_p50": order_stat(converged, 50),
                    "drift_converged_s_p95": order_stat(converged, 95),
                    "drift_never_converged": sum(c is None for c in converged)})
    if args.step_ms:
        rec = np.array([r["recovery_s"] for r in rows])
        oracle = np.array([r["oracle_recovery_s"] for r in rows])
        summary.update({"recovery_s_median": float(np.median(rec)),
                        "recovery_s_p90": round(float(np.percentile(rec, 90)), 2), "recovery_s_max": float(rec.max()),
                        "share_recovered_within_3s": float(np.mean(rec <= 3.0)),
                        "oracle_share_within_3s": float(np.mean(oracle <= 3.0))})
    for row in rows:
        print(json.dumps(row) if args.json else "  ".join(f"{k} {v}" for k, v in row.items()))
    print(json.dumps(summary) if args.json else "summary: " + "  ".join(f"{k} {v}" for k, v in summary.items()))


if __name__ == "__main__":
    main()
