"""Stateful random processes of a channel, vectorised over a batch of messages.

Each takes its per-message variates as arguments (drawn by the channel) and carries its
state from batch to batch, so a batch of n messages gives exactly what n calls of one
message give. Pure: no clock, no global randomness.
"""

from __future__ import annotations

import math

import numpy as np

from link_emulator.profile import OutageSpec
from link_emulator.trace import DelayTrace

NS_PER_S = 1_000_000_000
NS_PER_MS = 1_000_000


class GaussianAR1:
    """Correlated standard normal scores: z_k = rho z_{k-1} + sqrt(1 - rho^2) e_k, e_k ~ N(0, 1).

    With z_0 ~ N(0, 1) every z_k is N(0, 1) with lag-j correlation rho^j, so a jitter
    g(z_k) keeps its declared marginal distribution exactly (a Gaussian copula). netem's
    ``next = rho * previous + (1 - rho) * fresh`` on the delay itself would instead shrink
    the variance and change the distribution's shape; we do not use it.
    """

    def __init__(self, rho: float, z0: float) -> None:
        self.rho = rho
        self.z = z0

    def step_one(self, e: float) -> float:
        """The score for one innovation ``e``, which becomes the state (the per-message path: the
        arithmetic of ``step``'s lfilter)."""
        self.z = e if self.rho == 0.0 else self.rho * self.z + math.sqrt(1.0 - self.rho * self.rho) * e
        return self.z

    def step(self, e: np.ndarray) -> np.ndarray:
        """Scores for innovations ``e`` (shape (n,)); the last becomes the state."""
        if self.rho == 0.0 or e.size == 0:
            z = e
        elif e.size == 1:
            z = np.array([self.step_one(float(e[0]))])
        else:
            # y[k] = c e[k] + rho y[k-1] with y[-1] = z: lfilter([c], [1, -rho]) with zi = rho z
            from scipy.signal import lfilter  # (imported here: scipy.signal takes ~0.5 s, and the live
            #                                    per-message path never needs it)
            c = math.sqrt(1.0 - self.rho * self.rho)
            z, _ = lfilter([c], [1.0, -self.rho], e, zi=[self.rho * self.z])
        if z.size:
            self.z = float(z[-1])
        return z


class GilbertElliott:
    """Two-state loss chain per message (simple Gilbert): Good delivers, Bad loses.

    P(G -> B) = p, P(B -> G) = r. Stationary loss rate L = p / (p + r), mean burst
    (run of Bad) length B = 1 / r; so from (L, B): r = 1 / B, p = L r / (1 - L).
    Bernoulli loss is the special case r = 1 - L, p = L (B = 1 / (1 - L)), the shortest
    mean burst a rate L can have with p + r <= 1; shorter requested bursts are raised to it.

    One uniform u per message drives the step: u < p -> Bad; u >= 1 - r -> Good; else
    stay. Since p <= 1 - r, from Good this is Bad w.p. p and from Bad it is Good w.p. r,
    and no u swaps the states, so a batch is the last "set" event before each message.
    """

    def __init__(self, loss_probability: float, mean_burst_len: float | None, bad0: bool) -> None:
        loss = loss_probability
        if loss >= 1.0:
            self.p, self.r = 1.0, 0.0
        elif loss <= 0.0:
            self.p, self.r = 0.0, 1.0
        else:
            burst = max(mean_burst_len or 0.0, 1.0 / (1.0 - loss))
            self.r = 1.0 / burst
            self.p = min(1.0 - self.r, loss * self.r / (1.0 - loss))
        self.bad = bad0 and loss > 0.0

    @property
    def mean_burst_len(self) -> float:
        """Effective mean loss-burst length in messages (inf when everything is lost)."""
        return math.inf if self.r == 0.0 else 1.0 / self.r

    def step_one(self, u: float) -> bool:
        """Bad (lost) for one uniform ``u`` (the per-message path; the rule of ``step``)."""
        self.bad = True if u < self.p else False if u >= 1.0 - self.r else self.bad
        return self.bad

    def step(self, u: np.ndarray) -> np.ndarray:
        """Bad (lost) flags, shape (n,), for uniforms ``u``; the last becomes the state."""
        if u.size == 1:
            return np.array([self.step_one(float(u[0]))])
        event = np.where(u < self.p, 1, np.where(u >= 1.0 - self.r, 0, -1))  # 1 Bad, 0 Good, -1 stay
        positions = np.where(event >= 0, np.arange(u.size), -1)
        last = np.maximum.accumulate(positions) if u.size else positions
        bad = np.where(last >= 0, event[np.maximum(last, 0)] == 1, self.bad)
        if u.size:
            self.bad = bool(bad[-1])
        return bad


class OutageTimeline:
    """Down windows in ns after the channel's origin: scheduled ones and a random on/off process.

    The random windows are drawn lazily, in chunks, from their own generator, so how far
    the timeline has been extended never changes the per-message stream.
    """

    CHUNK = 256

    def __init__(self, spec: OutageSpec, rng: np.random.Generator) -> None:
        self.spec = spec
        self._rng = rng
        self._fixed = merge_windows([(a * NS_PER_S, b * NS_PER_S) for a, b in spec.windows_s])
        self._random_starts = np.empty(0)
        self._random_ends = np.empty(0)
        self._random_until_ns = 0.0  # end of the last generated window

    def down_until(self, rel_ns: np.ndarray) -> np.ndarray:
        """End (rel. ns) of the down window containing each time, NaN where the link is up."""
        until = _lookup(self._fixed[0], self._fixed[1], rel_ns) if self._fixed[0].size else None
        if self.spec.mean_interval_s is not None and rel_ns.size:
            self._extend_to(float(np.max(rel_ns)))
            random_until = _lookup(self._random_starts, self._random_ends, rel_ns)
            until = random_until if until is None else np.fmax(until, random_until)
        return np.full(rel_ns.shape, np.nan) if until is None else until

    def _extend_to(self, rel_ns: float) -> None:
        """Draw random windows until the timeline covers ``rel_ns``."""
        low_s, high_s = self.spec.duration_s
        while self._random_until_ns <= rel_ns:
            up_ns = self._rng.exponential(self.spec.mean_interval_s, self.CHUNK) * NS_PER_S
            down_ns = self._rng.uniform(low_s, high_s, self.CHUNK) * NS_PER_S
            ends = self._random_until_ns + np.cumsum(up_ns + down_ns)
            self._random_starts = np.concatenate((self._random_starts, ends - down_ns))
            self._random_ends = np.concatenate((self._random_ends, ends))
            self._random_until_ns = float(ends[-1])


def merge_windows(windows: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Sorted windows with overlaps merged, as (starts, ends) arrays."""
    merged: list[list[float]] = []
    for start, end in sorted(windows):
        if merged and start <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], end)
        else:
            merged.append([start, end])
    return np.array([w[0] for w in merged]), np.array([w[1] for w in merged])


def _lookup(starts: np.ndarray, ends: np.ndarray, t: np.ndarray) -> np.ndarray:
    """End of the window [start, end) containing each t (windows sorted, disjoint), else NaN."""
    if starts.size == 0:
        return np.full(t.shape, np.nan)
    index = np.searchsorted(starts, t, side="right") - 1
    inside = (index >= 0) & (t < ends[np.maximum(index, 0)])
    return np.where(inside, ends[np.maximum(index, 0)], np.nan)


class TraceClock:
    """Looped, order-keeping replay of a trace on its own (irregular) send times.

    Rows i = 0..n-1 of the trace (received messages): send time p_i (ns after row 0), delay
    d_i, arrival a_i = p_i + d_i; the trace loops every L ns, row n being row 0 of the next
    loop (p_n = L, d_n = d_0). A message sent at ``x = (t + phase) mod L`` falls in the row i
    with p_i <= x < p_{i+1}. Inside the gap's lost part (x >= p_{i+1} - m_i P, see
    ``DelayTrace.own_slot_ms``) it is lost. Otherwise it takes the delay of the nearer row in
    time, d_i before the midpoint c_i = (p_i + p_{i+1}) / 2 and d_{i+1} after it, except that
    a fall of the delay (d_{i+1} < d_i) becomes a FIFO drain centred on c_i: during
    ``d_i - d_{i+1}`` ns everything arrives at once, at h_i = c_i + (d_i + d_{i+1}) / 2:

        A(x) = min(x + d_i, h_i)       for x < c_i
        A(x) = max(x + d_{i+1}, h_i)   for x >= c_i

    (for a rise, h_i lies between the two branches and A simply steps up at c_i). Hence,
    for a trace that never reorders (a_i <= a_{i+1}, i.e. d_i - d_{i+1} <= p_{i+1} - p_i,
    every CICV5G run):

    - sent at a trace send time p_i, a message gets the trace's delay d_i exactly
      (a_i <= h_i <= a_{i+1});
    - every delay lies between the two neighbouring rows' (no inflation), and each row's
      delay holds for the half-intervals on both sides of it (less half a drain): nearest-row
      in time, so the time share of each value, and the quantiles, stay the trace's;
    - A never decreases (each branch is non-decreasing, A(c_i-) <= h_i <= A(c_i) and
      A(p_{i+1}-) = a_{i+1}), also across the loop seam (``DelayTrace.loop_ms`` makes
      L >= a_{n-1} - a_0): a later-sent message is never delivered before an earlier one.

    h_i is clamped to [a_i, max(a_i, a_{i+1})]: a no-op above except for ns rounding; for a
    trace that reorders, rows keep their delays and the replay reorders where the trace did.
    Times are integer ns, so equal arrival times stay exactly equal.
    """

    def __init__(self, trace: DelayTrace, phase_ns: int) -> None:
        self.loop_ns = round(trace.loop_ms * NS_PER_MS)
        self.send_ns = np.rint((trace.pub_time_ms - trace.pub_time_ms[0]) * NS_PER_MS).astype(np.int64)  # p_i
        self.row_delay_ns = np.rint(trace.delay_ms * NS_PER_MS).astype(np.int64)  # d_i, shape (n,)
        self.next_delay_ns = np.roll(self.row_delay_ns, -1)  # d_{i+1}
        next_send_ns = np.append(self.send_ns[1:], self.loop_ns)  # p_{i+1}
        self.lost_from_ns = next_send_ns - np.rint(trace.lost_after * trace.period_ms * NS_PER_MS).astype(np.int64)
        self.mid_ns = (self.send_ns + next_send_ns) // 2  # c_i
        arrive_ns = self.send_ns + self.row_delay_ns  # a_i
        next_arrive_ns = next_send_ns + self.next_delay_ns  # a_{i+1}
        held_ns = self.mid_ns + (self.row_delay_ns + self.next_delay_ns) // 2  # h_i
        self.held_ns = np.minimum(np.maximum(held_ns, arrive_ns), np.maximum(arrive_ns, next_arrive_ns))
        self.phase_ns = int(phase_ns) % self.loop_ns

    def delay_ns(self, rel_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Trace delay (int64 ns) of messages sent ``rel_ns`` (int, shape (n,)) after the origin, and lost flags."""
        x = (np.asarray(rel_ns, dtype=np.int64) + self.phase_ns) % self.loop_ns
        row = np.searchsorted(self.send_ns, x, side="right") - 1  # p_row <= x < p_{row+1}
        held = self.held_ns[row]
        arrive = np.where(x < self.mid_ns[row], np.minimum(x + self.row_delay_ns[row], held),
                          np.maximum(x + self.next_delay_ns[row], held))  # A(x)
        return arrive - x, x >= self.lost_from_ns[row]
