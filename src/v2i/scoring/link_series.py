"""Per-cycle RSU link samples of a run (what the OBU knew about each RSU, cycle by cycle), kept
compactly for the run report's timeline (``v2i.reports.run_report``).

The live driver feeds it from each ``ObuMetrics`` message (the OBU publishes one per cycle);
the offline runner from ``ObuPipeline.metrics`` after each cycle (``OfflineRun(link_series=True)``),
so both keep the same numbers: the OBU's one-way delay p50 / p95 over its 10 s window (RSU
publish stamp -> OBU receive, in OBU time), the age of the newest RSU frame at the cycle, the
clock offset estimate and its uncertainty, and the lists accepted so far.

Per RSU per sample 41 bytes: t_ns 8, RSU code 1, delay p50 / p95 and data age 4 each (float32
ms), offset and uncertainty 8 each (float64 ns), accepted count 4. Unknown values are NaN.
"""

from __future__ import annotations

from array import array
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from schemas.messages import RsuLinkStatus

MAX_RSUS = 255  # RSU codes are one byte; a site has at most 62 RSUs (scenario limit)


@dataclass(frozen=True)
class RsuSamples:
    """One RSU's samples, in sample order; every array (K,): t_ns int64 (OBU clock), delay p50 /
    p95 and data age (ms), clock offset estimate theta = rsu - obu and its uncertainty (ns),
    lists accepted so far (int64). NaN where the OBU knew nothing yet."""

    rsu_id: str
    t_ns: np.ndarray
    delay_p50_ms: np.ndarray
    delay_p95_ms: np.ndarray
    age_ms: np.ndarray
    offset_ns: np.ndarray
    uncertainty_ns: np.ndarray
    accepted: np.ndarray


def _nan(value: float | None) -> float:
    return float("nan") if value is None else float(value)


class LinkSeries:
    """Append-only per-RSU samples (module doc); RSU ids get a one-byte code in order of appearance."""

    def __init__(self):
        self.rsu_ids: list[str] = []
        self._t_ns, self._rsu = array("q"), array("B")
        self._ms = (array("f"), array("f"), array("f"))  # delay p50, delay p95, data age
        self._ns = (array("d"), array("d"))  # offset, uncertainty
        self._accepted = array("I")

    def __len__(self) -> int:
        return len(self._t_ns)

    def add(self, t_ns: int, rsus: Sequence[RsuLinkStatus]) -> None:
        """One sample per RSU the OBU reports at ``t_ns`` (OBU clock)."""
        for status in rsus:
            if status.rsu_id not in self.rsu_ids:
                if len(self.rsu_ids) >= MAX_RSUS:
                    continue  # more RSUs than a site can have: not plotted
                self.rsu_ids.append(status.rsu_id)
            self._t_ns.append(int(t_ns))
            self._rsu.append(self.rsu_ids.index(status.rsu_id))
            for column, value in zip(self._ms, (status.delay_p50_ms, status.delay_p95_ms, status.last_data_age_ms)):
                column.append(_nan(value))
            for column, value in zip(self._ns, (status.clock_offset_ns, status.clock_uncertainty_ns)):
                column.append(_nan(value))
            self._accepted.append(min(status.messages_accepted, 2**32 - 1))

    def per_rsu(self) -> list[RsuSamples]:
        """Each RSU's samples, RSUs in order of appearance."""
        codes = np.frombuffer(self._rsu, dtype=np.uint8) if len(self._rsu) else np.zeros(0, np.uint8)
        t_ns = np.array(self._t_ns, dtype=np.int64)
        ms = [np.array(c, dtype=float) for c in self._ms]
        ns = [np.array(c, dtype=float) for c in self._ns]
        accepted = np.array(self._accepted, dtype=np.int64)
        out = []
        for code, rsu_id in enumerate(self.rsu_ids):
            rows = np.flatnonzero(codes == code)
            out.append(RsuSamples(rsu_id, t_ns[rows], *(c[rows] for c in ms), *(c[rows] for c in ns), accepted[rows]))
        return out
