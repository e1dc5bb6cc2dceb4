"""What TS 103 324's CPM generation rules (``--cpm-rules``) save on the wire, and what they cost the OBU.

    python benchmarks/cpm_rules.py                          # dense-intersection, seeds 0-4
    python benchmarks/cpm_rules.py --seeds 0,1 --scenario red-light-runner

Per seed, the same ``v2i eval --wire cpm`` run twice, without and with ``--cpm-rules``: the RSUs'
CPM bytes per second (``OfflineRun.rsu_lists_sent``: every object list as sent, segments each),
and the OBU's overall detection mAP, MOTA, and the target's BEV IoU and RMSE; then the means.
One JSON line per seed, then one for the means (``--json``: only those lines).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from v2i.offline.runner import OfflineRun  # noqa: E402
from v2i.offline.spec import RunSpec  # noqa: E402


def scores(scenario: str, seed: int, rules: bool) -> dict:
    """One run's bytes and accuracy."""
    run = OfflineRun(RunSpec(scenario=scenario, wire="cpm", seed=seed, cpm_rules=rules))
    run.execute()
    report, lists = run.report(), run.rsu_lists_sent()
    return {"bytes_per_s": lists["bytes_per_s"], "messages": lists["messages"],
            "mAP": round(report["detection"]["overall"]["mAP"], 4), "mota": round(report["tracking"]["mota"], 4),
            "target_iou": report["target"]["mean_bev_iou"], "target_rmse_m": report["target"]["rmse_m"]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="dense-intersection")
    p.add_argument("--seeds", default="0,1,2,3,4", help="comma-separated (default %(default)s)")
    p.add_argument("--json", action="store_true", help="JSON lines only")
    args = p.parse_args()
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        every, ruled = scores(args.scenario, seed, False), scores(args.scenario, seed, True)
        delta = {k: None if every[k] is None or ruled[k] is None else round(ruled[k] - every[k], 4)
                 for k in ("bytes_per_s", "mAP", "mota", "target_iou", "target_rmse_m")}
        rows.append({"seed": seed, "every_object": every, "cpm_rules": ruled, "delta": delta,
                     "saved_pct": round(100.0 * (1.0 - ruled["bytes_per_s"] / every["bytes_per_s"]), 1)})
        print(json.dumps(rows[-1]), flush=True)
    means = {k: round(statistics.mean(r["delta"][k] for r in rows if r["delta"][k] is not None), 4)
             for k in rows[0]["delta"]}
    print(json.dumps({"scenario": args.scenario, "seeds": len(rows), "mean_delta": means,
                      "mean_saved_pct": round(statistics.mean(r["saved_pct"] for r in rows), 1)}))
    if not args.json:
        print(f"{args.scenario}: --cpm-rules saves {-means['bytes_per_s']:.0f} B/s "
              f"({statistics.mean(r['saved_pct'] for r in rows):.1f} %); mAP {means['mAP']:+.3f}, "
              f"MOTA {means['mota']:+.3f}, target IoU {means['target_iou']:+.3f}, "
              f"RMSE {means['target_rmse_m']:+.3f} m (mean of {len(rows)} seeds)", file=sys.stderr)


if __name__ == "__main__":
    main()
