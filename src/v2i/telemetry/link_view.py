"""What a link emulator's stats say (pure): counters, drop ratios, impairments in force.

Reads the JSON of ``v2x/link/{id}/stats`` (``link_emulator.relay.stats_snapshot`` for an RSU
link: ``uplink`` / ``downlink``; ``link_emulator.v2v_relay``: ``mode: v2v`` and ``v2v``)
defensively: a field of the wrong type reads as absent, never raises.

Impairments in force are not a field of the stats; they follow from ``control.recent``, the
emulator's outcome of each ``LinkControl`` (``link_emulator.control.apply_control``'s text,
e.g. ``"outage on both for 3 s"``): an impairment counts from the stats time at which its
outcome first appeared until that time plus its duration, and ``"impairments cleared"`` ends
those seen before it. The start is late by at most one stats period (1 s by default).
"""

from __future__ import annotations

import math
import re
from typing import Any

from v2i.telemetry.windowed import WindowedCounters, ratio

DIRECTION_KEYS = ("downlink", "uplink", "v2v")
MAX_IMPAIRMENTS = 16  # in force at once, per link (the emulator repeats its latest 16 outcomes)
MAX_OUTCOMES_SEEN = 256  # control outcomes remembered, so that each is counted once
MAX_PAIRS_SHOWN = 64
MAX_DURATION_S = 86_400.0  # LinkControl.duration_s's bound
MAX_TEXT = 120  # characters of an outcome text kept
_FOR_S = re.compile(r" for ([0-9.eE+-]+) s$")


def _seconds(digits: str) -> float | None:
    """The float in ``digits`` (an outcome's duration), or None when it is not one."""
    try:
        return number(float(digits))
    except ValueError:
        return None


def count(value: Any) -> int | None:
    """``value`` if it is a non-negative int (not a bool), else None."""
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 0 else None


def number(value: Any) -> float | None:
    """``value`` as a float if it is a finite int or float (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def text(value: Any, limit: int = 64) -> str | None:
    """``value`` cut to ``limit`` characters if it is a string, else None."""
    return value[:limit] if isinstance(value, str) else None


def counts(value: Any, limit: int = 64) -> dict[str, int]:
    """The ``{str: non-negative int}`` entries of ``value`` (at most ``limit``), others skipped."""
    if not isinstance(value, dict):
        return {}
    out: dict[str, int] = {}
    for k, v in value.items():
        if len(out) >= limit:
            break
        if isinstance(k, str) and count(v) is not None:
            out[k[:64]] = v
    return out


def direction_view(stats: Any) -> dict[str, Any] | None:
    """One direction's counters and delays (ms) from its stats dict, or None when it has none."""
    if not isinstance(stats, dict):
        return None
    delay = stats.get("delay_ms") if isinstance(stats.get("delay_ms"), dict) else {}
    received, dropped = count(stats.get("received")), count(stats.get("dropped"))
    return {"received": received, "delivered": count(stats.get("delivered")), "dropped": dropped,
            "drop_ratio": ratio(dropped or 0, received or 0),
            "delay_mean_ms": number(delay.get("mean")), "delay_max_ms": number(delay.get("max"))}


def latency_view(value: Any, limit: int = 32) -> dict[str, dict[str, float | int | None]] | None:
    """The stats' ``latency_ms`` (stage -> count, p50, p95, p99 in ms; ``v2i.telemetry.latency``), or None."""
    if not isinstance(value, dict) or not value:
        return None
    return {stage[:32]: {"count": count(q.get("count")), **{k: number(q.get(k)) for k in ("p50", "p95", "p99")}}
            for stage, q in list(value.items())[:limit] if isinstance(stage, str) and isinstance(q, dict)}


class LinkView:
    """The latest stats of one link emulator, drop ratios over a window and impairments in force."""

    def __init__(self, link_id: str, window_ns: int):
        self.link_id = link_id
        self.messages = 0
        self.last_receive_ns = 0
        self.latest: dict[str, Any] = {}
        self._window = WindowedCounters(window_ns)
        self._seen: dict[tuple[int | None, str], int] = {}  # (seq, outcome) -> stats time_ns first seen
        self._impairments: list[dict[str, Any]] = []  # {"effect", "from_ns", "until_ns"}

    def update(self, stats: dict[str, Any], receive_ns: int) -> None:
        """Take one stats message (already a dict) received at ``receive_ns``."""
        self.messages += 1
        self.last_receive_ns = receive_ns
        t_ns = count(stats.get("time_ns")) or 0
        directions = {k: v for k in DIRECTION_KEYS if (v := direction_view(stats.get(k))) is not None}
        totals = {f"{d}_{c}": v[c] for d, v in directions.items() for c in ("received", "dropped") if v[c] is not None}
        self._window.add(receive_ns, totals)
        control = stats.get("control") if isinstance(stats.get("control"), dict) else {}
        self._note_outcomes(control.get("recent"), t_ns)
        lateness = stats.get("lateness_ms") if isinstance(stats.get("lateness_ms"), dict) else {}
        pairs = stats.get("pairs") if isinstance(stats.get("pairs"), list) else []
        self.latest = {
            "kind": "v2v" if stats.get("mode") == "v2v" else "rsu", "profile": text(stats.get("profile")),
            "time_ns": t_ns, "directions": directions,
            "lateness_mean_ms": number(lateness.get("mean")), "lateness_max_ms": number(lateness.get("max")),
            "refused": counts(stats.get("refused")), "controls_applied": count(control.get("applied")),
            "controls_rejected": counts(control.get("rejected")),
            "latency_ms": latency_view(stats.get("latency_ms")),
            "pairs": [{"vehicle_id": text(p.get("vehicle_id")), "profile": text(p.get("profile"))}
                      for p in pairs[:MAX_PAIRS_SHOWN] if isinstance(p, dict)],
        }

    def _note_outcomes(self, recent: Any, t_ns: int) -> None:
        """Impairments from the applied control outcomes not seen before (``recent`` as the stats give it)."""
        for outcome in recent if isinstance(recent, list) else []:
            result = text(outcome.get("result"), MAX_TEXT) if isinstance(outcome, dict) else None
            if result is None:
                continue  # a rejected control, or not an outcome
            key = (count(outcome.get("seq")), result)
            if key in self._seen:
                continue
            self._seen[key] = t_ns
            if len(self._seen) > MAX_OUTCOMES_SEEN:
                del self._seen[next(iter(self._seen))]
            self._apply_outcome(result, t_ns)

    def _apply_outcome(self, result: str, t_ns: int) -> None:
        if result.startswith("impairments cleared"):
            self._impairments = [i for i in self._impairments if i["from_ns"] > t_ns]
            return
        match = _FOR_S.search(result)
        duration_s = _seconds(match.group(1)) if match else None
        if duration_s is None or not 0 < duration_s <= MAX_DURATION_S:
            return  # a profile switch: the profile field shows it
        effect = result[:match.start()]
        self._impairments.append({"effect": effect, "from_ns": t_ns, "until_ns": t_ns + round(duration_s * 1e9)})
        del self._impairments[:-MAX_IMPAIRMENTS]

    def in_force(self) -> list[dict[str, Any]]:
        """Impairments whose window covers the latest stats time: effect and seconds left."""
        t_ns = self.latest.get("time_ns", 0)
        return [{"effect": i["effect"], "left_s": round((i["until_ns"] - t_ns) * 1e-9, 1)}
                for i in self._impairments if i["from_ns"] <= t_ns < i["until_ns"]]

    def snapshot(self, now_ns: int) -> dict[str, Any]:
        """The link's JSON-ready view (see ``v2i.telemetry.snapshot`` for the keys)."""
        span_s, delta = self._window.delta()
        recent = {d: ratio(delta.get(f"{d}_dropped", 0), delta.get(f"{d}_received", 0))
                  for d in self.latest.get("directions", {})}
        return {"messages": self.messages, "age_s": round((now_ns - self.last_receive_ns) * 1e-9, 2),
                **self.latest, "drop_ratio_window": recent, "window_span_s": round(span_s, 2),
                "impairments": self.in_force()}
