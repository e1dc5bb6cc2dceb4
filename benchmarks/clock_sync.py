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
- unbounded: share of scored times where |error| > the stated uncertainty.

    python benchmarks/clock_sync.py [--profile iaad-field] [--seeds 1-50] [--step-ms 500] [--json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from link_emulator.channel import Channel, LinkModel
from link_emulator.profile import load_profile
from v2i.clock.clock_sync import NS_PER_S
from v2i.sim.sync_sim import exchanges, run_sync
from v2i.sim.clock import ClockStep, DriftingClock, SimClock

T0 = 1_767_225_600 * NS_PER_S
NS_PER_MS = 1_000_000
GRID_NS = 100 * NS_PER_MS


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
    run = run_sync(clock, samples, T0, round(args.duration_s * NS_PER_S), grid_ns=GRID_NS)
    scored = run.t_ns >= 5 * NS_PER_S
    rel_step_ns = step_at_ns - T0
    if steps:
        scored &= ~((run.t_ns >= rel_step_ns) & (run.t_ns < rel_step_ns + 3 * NS_PER_S))
    err_ms = np.abs(run.error_ns[scored]) / NS_PER_MS
    out = {"seed": seed, "p95_ms": round(float(np.percentile(err_ms, 95)), 3),
           "max_ms": round(float(err_ms.max()), 3),
           "unbounded": round(float(np.mean(np.abs(run.error_ns[scored]) > run.uncertainty_ns[scored])), 4),
           "uncertainty_p50_ms": round(float(np.median(run.uncertainty_ns[scored])) / NS_PER_MS, 2),
           "steps": run.steps_detected}
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
