"""A channel's per-message path: one message through a plain channel in Python floats.

The live relay and the offline evaluator send one message per call; on a plain channel (no
impairment window, outage schedule, trace replay or rate cap: ``Channel._plain``) stages 1, 2
and the trace of ``link_emulator.channel`` pass it unchanged, so only the loss chain, the distance
PDR, the delay and the order are left. ``ScalarPath`` (a part of ``Channel``) does those with the
same variates, the same state steps in the same order and the same float64 arithmetic as the
batch (numpy) path, so a message gets the same deliveries either way (tests/unit/test_link_channel.py,
test_link_channel_scalar.py):

    lost = chain(u_loss) or (d known and u_pdr >= PDR(d));  dup = not lost and u_dup < p_dup
    deliver = send + rint(max(0, delay_ms + g(z) [+ spike]) ms);  copy = send + rint(max(0, delay_ms + g(z_dup)) ms)
    fifo: each delivery is at least the latest so far
"""

from __future__ import annotations

import math
from bisect import bisect_right

import numpy as np

from link_emulator.processes import NS_PER_MS

NONE_NS = -1  # "no delivery" (channel.NONE_NS)
# per-message variates: normals (jitter innovation, spike size, duplicate's jitter),
# uniforms (loss chain, distance PDR, spike occurrence, duplication, impairment loss)
_Z_JITTER, _Z_SPIKE, _Z_DUP = range(3)
_U_LOSS, _U_PDR, _U_SPIKE, _U_DUP, _U_IMPAIR = range(5)


class ScalarPath:
    """``Channel``'s per-message methods (its state: ``direction``, ``_draws``, ``_ge``, ``_ar``,
    ``_pdr_curve``, ``_g_kept``, ``_origin_ns``, ``_last_ns``)."""

    def _transmit_one(self, send_ns: int, size_bytes: int, distance_m: float | None) -> list[int]:
        """``transmit_all`` on a plain channel (``_plain``) in Python floats: the same variates, the
        same state steps (loss chain, AR(1), fifo) in the same order and the same float64 delay
        arithmetic, the jitter's g(z) by the same numpy expression (``_block_g``, ``_jitter_ms``), so
        the same deliveries, ascending (test_link_channel)."""
        if size_bytes < 0:
            raise ValueError(f"size_bytes must be >= 0, got {size_bytes}")
        k, z, u = self._draws.take_one()
        if self._origin_ns is None:
            self._origin_ns = send_ns
        d = self.direction
        lost = self._ge.step_one(u[_U_LOSS][k])
        if distance_m is not None and not math.isnan(distance_m):
            lost = (u[_U_PDR][k] >= self._pdr_one(float(distance_m))) or lost  # delivered with probability PDR(d)
        z_jitter = self._ar.step_one(z[_Z_JITTER][k])  # steps the AR(1) always
        if lost:
            return []
        # without correlation the score is the block's own normal: its g(z) is the block's
        jitter_ms = self._block_g(d.jitter, _Z_JITTER, k) if self._ar.rho == 0.0 else _jitter_ms(d.jitter, z_jitter)
        delay_ms = d.delay_ms + jitter_ms
        if d.spikes is not None and u[_U_SPIKE][k] < d.spikes.probability:
            delay_ms = delay_ms + self._block_g(d.spikes.extra, _Z_SPIKE, k)
        deliver_ns = self._in_order_one(send_ns + round(max(delay_ms, 0.0) * NS_PER_MS))  # _clipped_ns
        if not u[_U_DUP][k] < d.duplicate_probability:
            return [deliver_ns]
        copy_ms = d.delay_ms + self._block_g(d.jitter, _Z_DUP, k)
        copy_ns = self._in_order_one(send_ns + round(max(copy_ms, 0.0) * NS_PER_MS))
        return [deliver_ns, copy_ns] if deliver_ns <= copy_ns else [copy_ns, deliver_ns]

    def _in_order_one(self, t_ns: int) -> int:
        """One delivery (not NONE_NS) after the latest so far: the latest with ``fifo``, else itself."""
        if t_ns > self._last_ns:
            self._last_ns = t_ns
        return self._last_ns if self.direction.fifo else t_ns

    def _block_g(self, jitter, column: int, k: int) -> float:
        """g(z) (ms) of row k of a column of the current block of normals: ``jitter``'s numpy expression
        over the whole column (elementwise, so each entry is what ``_jitter_ms`` of the one score
        gives), computed once per block, column and jitter (a profile switch brings another)."""
        block = self._draws.normal
        kept = self._g_kept.get(column)
        if kept is None or kept[0] is not block or kept[1] is not jitter:
            kept = self._g_kept[column] = (block, jitter, jitter.from_normal(block[:, column]).tolist())
        return kept[2][k]

    def _pdr_one(self, distance_m: float) -> float:
        """``direction.pdr_at`` of one distance (m): np.interp's rule on the curve's points, taken apart
        once per profile (``set_direction``), in Python floats (``_interp``)."""
        d = self.direction
        if d.range_m is not None and distance_m > d.range_m:
            return 0.0
        return 1.0 if self._pdr_curve is None else _interp(distance_m, *self._pdr_curve)

    def _one_in_order(self, deliver_ns: int, copy_ns: int) -> tuple[int, int]:
        """``_in_order`` of one message and its copy (NONE_NS: none), as ints."""
        out = []
        for t_ns in (deliver_ns, copy_ns):
            if t_ns != NONE_NS:
                self._last_ns = max(self._last_ns, t_ns)
                t_ns = self._last_ns if self.direction.fifo else t_ns
            out.append(t_ns)
        return out[0], out[1]


def _interp(x: float, xp: list[float], fp: list[float]) -> float:
    """``np.interp(x, xp, fp)`` of one number x (not NaN), xp strictly increasing: the held end values
    outside, a point's own value on it, else the same float steps, slope (fp[j+1] - fp[j]) /
    (xp[j+1] - xp[j]) times (x - xp[j]) plus fp[j] (numpy's arr_interp; test_link_channel)."""
    j = bisect_right(xp, x) - 1  # xp[j] <= x < xp[j + 1]
    if j < 0:
        return fp[0]
    if j == len(xp) - 1 or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    y = slope * (x - xp[j]) + fp[j]
    if math.isnan(y):  # numpy's retry from the other end (a non-finite slope)
        y = slope * (x - xp[j + 1]) + fp[j + 1]
        if math.isnan(y) and fp[j] == fp[j + 1]:
            y = fp[j]
    return y


def _jitter_ms(jitter, z: float) -> float:
    """g(z) of one score (ms) by the jitter's own numpy expression, as in the batch (its exp, ndtr or
    log_ndtr, not math's, which may differ in the last bit)."""
    return float(jitter.from_normal(np.array([z]))[0])


def _clipped_ns(delay_ms: float) -> int:
    """``_clipped_sum_ns`` of one delay without a trace: rint(max(0, delay) ms) ns (round: half to
    even, as np.rint)."""
    return round(max(delay_ms, 0.0) * NS_PER_MS)
