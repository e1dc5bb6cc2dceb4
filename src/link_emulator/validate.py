"""Validation of a link profile: what the channel model achieves beside what the profile declares.

``validate_direction`` pushes N messages (sent every ``interval_ms``, ``size_bytes`` each)
through a seeded ``Channel`` and summarises delivered delays and losses; ``declared``
derives the same numbers from the profile:

- delay (mean, p50, p95, p99 of max(0, delay_ms + J) + serialization 8 size / rate):
  analytic from the jitter's quantile function (for empirical jitter, the quantiles of its
  samples); for a trace replay, the trace's own delays; with spikes, or a trace plus
  jitter, a Monte Carlo of the declared distribution. Queueing, fifo hold and outage hold
  are emergent effects, not part of the declaration. Every sample quantile, declared or
  achieved, is taken with the same definition (``quantile_ms``), so an exact replay of a
  trace gives exactly the trace's quantiles.
- loss ratio, analytic for independent mechanisms:
  1 - (1 - down fraction)(1 - loss_probability) PDR(d) (1 - trace loss), the trace loss
  being the lost share of its send time (``DelayTrace.loss_ratio``).
- mean loss-burst length (messages): analytic for a single mechanism (Bernoulli:
  1 / (1 - L); Gilbert-Elliott: its B), else a Monte Carlo of the declared loss processes
  drawn by an independent algorithm (geometric run lengths, separately drawn outage
  windows, a trace's gaps as time windows; not the channel's code). Time-based losses
  (outages, trace gaps) give bursts that depend on ``interval_ms``: a trace's irregular
  send times can join two of its gaps for a sender in step with its median period.

Acceptance (``checks``): loss ratio within 10 %; the achieved median inside the range that
sampling error allows at the delivered sample count (``p50_range_ms``); for a trace replay,
p99 within 3 ms of the trace's and, when the trace itself never reorders and nothing random
is added to it, no delivery overtaken by a later-sent message (``overtaken_ratio``).

Pure: no I/O; the CLI in ``cli.py`` prints the result.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
from scipy.special import ndtri

from link_emulator.channel import NS_PER_MS, Channel
from link_emulator.processes import GilbertElliott, merge_windows
from link_emulator.profile import DirectionProfile
from link_emulator.trace import DelayTrace, load_trace, mean_run_length, overtaken_ratio

QUANTILES = {"p50_ms": 0.50, "p95_ms": 0.95, "p99_ms": 0.99}
MONTE_CARLO_SAMPLES = 2_000_000
CHUNK = 100_000  # messages per transmit_batch call (bounds memory; results do not depend on it)
T0_NS = 1_700_000_000 * 10**9
QUANTILE_METHOD = "inverted_cdf"  # numpy's name for Q(q) = min{x : F_n(x) >= q}, see quantile_ms
LOSS_RTOL = 0.10  # acceptance: achieved loss within 10 % of declared
P50_Z = 4.0  # acceptance: achieved p50 within 4 standard errors (in probability) of the declared median
TRACE_P99_ATOL_MS = 3.0  # acceptance for trace replays: p99 within 3 ms of the trace's


@dataclass(frozen=True)
class Summary:
    """Delay statistics of delivered messages (ms) and loss statistics (ratio, messages)."""

    mean_ms: float | None
    p50_ms: float | None
    p95_ms: float | None
    p99_ms: float | None
    loss_ratio: float
    mean_burst_len: float

    def as_dict(self) -> dict[str, float | None]:
        """JSON-safe: non-finite values become None."""
        return {k: (v if v is not None and math.isfinite(v) else None) for k, v in asdict(self).items()}


@dataclass(frozen=True)
class Settings:
    """How the validation traffic is sent."""

    samples: int = 100_000
    seed: int = 0
    interval_ms: float = 100.0
    size_bytes: int = 1000
    distance_m: float | None = None


def quantile_ms(values_ms: np.ndarray, q: np.ndarray | float) -> np.ndarray:
    """Sample q-quantile(s) of ``values_ms`` (shape (k,)): Q(q) = min{x : F_n(x) >= q}.

    The one definition used for declared and achieved values: it is the exact quantile
    function of an empirical law (a trace, empirical jitter), so replaying a trace gives its
    quantiles exactly, and it converges to Q(q) of a continuous law. (numpy's default linear
    interpolation would put a trace's p99 between two of its values, where a long replay,
    whose order statistics repeat each value, never lands.)
    """
    return np.quantile(values_ms, q, method=QUANTILE_METHOD)


def summarise(delays_ms: np.ndarray, lost: np.ndarray) -> Summary:
    """Summary of delivered delays (ms, shape (k,)) and per-message loss flags (shape (n,))."""
    stats = {k: float(quantile_ms(delays_ms, q)) if delays_ms.size else None for k, q in QUANTILES.items()}
    mean_ms = float(delays_ms.mean()) if delays_ms.size else None
    return Summary(mean_ms, **stats, loss_ratio=float(np.mean(lost)), mean_burst_len=mean_run_length(lost))


def achieved(direction: DirectionProfile, settings: Settings, direction_name: str = "downlink") -> tuple[np.ndarray, np.ndarray]:
    """Delays (ms) of delivered messages and loss flags of ``settings.samples`` messages.

    The channel's generator is the one ``LinkModel(profile, seed)`` gives that direction, so
    the run is exactly what the live relay or the evaluator would draw for this traffic.
    """
    uplink_seq, downlink_seq = np.random.SeedSequence(settings.seed).spawn(2)
    channel = Channel(direction, np.random.default_rng(uplink_seq if direction_name == "uplink" else downlink_seq))
    interval_ns = round(settings.interval_ms * NS_PER_MS)
    delays, lost = [], []
    for start in range(0, settings.samples, CHUNK):
        send_ns = T0_NS + interval_ns * np.arange(start, min(start + CHUNK, settings.samples), dtype=np.int64)
        out = channel.transmit_batch(send_ns, settings.size_bytes, settings.distance_m)
        delays.append((out.deliver_ns[~out.lost] - send_ns[~out.lost]) / NS_PER_MS)
        lost.append(out.lost)
    return np.concatenate(delays), np.concatenate(lost)


# ---- declared values -----------------------------------------------------------------------


def serialization_ms(direction: DirectionProfile, size_bytes: int) -> float:
    """s = 8 size / R: bits / (kbit/s) = ms; 0 without a rate."""
    return 0.0 if direction.bandwidth_kbps is None else 8.0 * size_bytes / direction.bandwidth_kbps


@dataclass(frozen=True)
class DelayLaw:
    """A declared delay law of delivered messages (ms) and how it was obtained.

    ``quantile_ms(q)``: its quantile function, q in [0, 1] (array or scalar); ``draws``: the
    size of the random sample it is estimated from (inf when exact: analytic, or the very
    samples the channel draws from, a trace or empirical jitter).
    """

    method: str
    mean_ms: float
    quantile_ms: Callable[[np.ndarray], np.ndarray]
    draws: float = math.inf


def declared_law(direction: DirectionProfile, settings: Settings) -> DelayLaw:
    """The declared law of the delivered delay; see the module docstring."""
    s_ms = serialization_ms(direction, settings.size_bytes)
    jitter, base = direction.jitter, direction.delay_ms
    if direction.spikes is None and direction.replay is None:
        if jitter.distribution == "empirical":
            return _sample_law("analytic", np.maximum(0.0, base + jitter.sorted_ms) + s_ms, math.inf)

        def analytic_quantile_ms(q: np.ndarray) -> np.ndarray:
            # Q(q) = max(0, base + g(Phi^-1(q))) + s: clipping at 0 is monotone, so it commutes
            return np.maximum(0.0, base + jitter.from_normal(ndtri(np.asarray(q, dtype=float)))) + s_ms

        return DelayLaw("analytic", jitter.mean_clipped_ms(base) + s_ms, analytic_quantile_ms)
    if direction.replay is not None and direction.spikes is None and jitter.distribution == "none":
        return _sample_law("trace", base + trace_delays_ms(direction) + s_ms, math.inf)
    values = _monte_carlo_delays_ms(direction, np.random.default_rng([settings.seed, 1])) + s_ms
    return _sample_law("monte-carlo", values, MONTE_CARLO_SAMPLES)


def _sample_law(method: str, values_ms: np.ndarray, draws: float) -> DelayLaw:
    """The law whose quantiles are those of ``values_ms`` (shape (k,)), by ``quantile_ms``."""
    values_ms = np.sort(values_ms)
    return DelayLaw(method, float(values_ms.mean()), lambda q: quantile_ms(values_ms, q), draws)


def trace_delays_ms(direction: DirectionProfile) -> np.ndarray:
    """The replayed trace's delays of received messages (ms)."""
    return load_trace(direction.replay.trace).delay_ms


def _monte_carlo_delays_ms(direction: DirectionProfile, rng: np.random.Generator) -> np.ndarray:
    """MONTE_CARLO_SAMPLES i.i.d. draws of max(0, delay_ms + J + spike + trace) (ms)."""
    n = MONTE_CARLO_SAMPLES
    delay_ms = direction.delay_ms + direction.jitter.from_normal(rng.standard_normal(n))
    if direction.spikes is not None:
        spiking = rng.random(n) < direction.spikes.probability
        delay_ms = delay_ms + np.where(spiking, direction.spikes.extra.from_normal(rng.standard_normal(n)), 0.0)
    if direction.replay is not None:
        delay_ms = delay_ms + rng.choice(trace_delays_ms(direction), n)
    return np.maximum(delay_ms, 0.0)


def down_fraction(direction: DirectionProfile, settings: Settings) -> float:
    """Declared fraction of messages sent while a ``drop`` outage is on."""
    spec = direction.outage
    if spec is None or spec.mode != "drop":
        return 0.0
    span_s = settings.samples * settings.interval_ms / 1000.0
    scheduled_s = sum(max(0.0, min(end, span_s) - start) for start, end in _union(list(spec.windows_s)))
    random_f = spec.random_down_fraction()
    # independent scheduled and random windows: P(up) = P(up scheduled) P(up random)
    return 1.0 - (1.0 - scheduled_s / span_s) * (1.0 - random_f)


def declared_loss(direction: DirectionProfile, settings: Settings) -> tuple[float, float, str]:
    """Declared loss ratio, mean burst length (messages) and how the burst length was obtained."""
    factors = _loss_factors(direction, settings)
    loss = 1.0 - math.prod(1.0 - f for f in factors.values())
    active = {k for k, f in factors.items() if f > 0.0}
    if not active:
        return 0.0, 0.0, "analytic"
    if loss >= 1.0:
        return 1.0, math.inf, "analytic"
    ge = GilbertElliott(direction.loss_probability, direction.mean_burst_len, False)
    bursty_chain = direction.loss_probability > 0.0 and ge.mean_burst_len > 1.0 / (1.0 - direction.loss_probability) + 1e-12
    if active <= {"chain", "distance"} and not bursty_chain:
        return loss, 1.0 / (1.0 - loss), "analytic"  # independent Bernoulli losses: geometric runs
    if active == {"chain"}:
        return loss, ge.mean_burst_len, "analytic"
    flags = _monte_carlo_loss_flags(direction, settings, np.random.default_rng([settings.seed, 2]))
    return loss, mean_run_length(flags), "monte-carlo"


def _loss_factors(direction: DirectionProfile, settings: Settings) -> dict[str, float]:
    """Loss probability of each independent mechanism."""
    pdr = 1.0 if settings.distance_m is None else float(direction.pdr_at(settings.distance_m))
    trace_loss = 0.0 if direction.replay is None else load_trace(direction.replay.trace).loss_ratio
    return {
        "outage": down_fraction(direction, settings),
        "chain": direction.loss_probability,
        "distance": 1.0 - pdr,
        "trace": trace_loss,
    }


def _monte_carlo_loss_flags(direction: DirectionProfile, settings: Settings, rng: np.random.Generator) -> np.ndarray:
    """Loss flags of the declared processes over MONTE_CARLO_SAMPLES messages, drawn independently."""
    n = max(settings.samples, MONTE_CARLO_SAMPLES)
    t_s = np.arange(n) * settings.interval_ms / 1000.0
    lost = _gilbert_runs(direction.loss_probability, direction.mean_burst_len, n, rng)
    if settings.distance_m is not None:
        lost |= rng.random(n) >= float(direction.pdr_at(settings.distance_m))
    if direction.outage is not None and direction.outage.mode == "drop":
        lost |= _in_windows(t_s, _outage_windows_s(direction, float(t_s[-1]), rng))
    if direction.replay is not None:
        trace = load_trace(direction.replay.trace)
        loop_s = trace.loop_ms / 1000.0
        lost |= _in_windows((t_s + rng.uniform(0.0, loop_s)) % loop_s, _trace_gaps_s(trace))
    return lost


def _trace_gaps_s(trace: DelayTrace) -> list[tuple[float, float]]:
    """The lost send windows of one loop of ``trace``, in s after its first row: the last m P of each gap."""
    end_s = (np.append(trace.pub_time_ms[1:], trace.pub_time_ms[0] + trace.loop_ms) - trace.pub_time_ms[0]) / 1000.0
    lost_s = trace.lost_after * trace.period_ms / 1000.0
    return [(e - w, e) for e, w in zip(end_s, lost_s) if w > 0.0]


def _gilbert_runs(loss: float, burst_len: float | None, n: int, rng: np.random.Generator) -> np.ndarray:
    """Gilbert chain flags built from alternating geometric runs: Bad ~ Geom(r), Good ~ Geom(p)."""
    ge = GilbertElliott(loss, burst_len, False)
    if ge.p == 0.0:
        return np.zeros(n, dtype=bool)
    if ge.r == 0.0:
        return np.ones(n, dtype=bool)
    pairs = int(n * ge.p * 1.2) + 16  # expected Good+Bad run pairs in n messages: n p r / (p + r) <= n p
    good, bad = rng.geometric(ge.p, pairs), rng.geometric(ge.r, pairs)
    start_bad = rng.random() < loss
    runs = np.column_stack((bad, good) if start_bad else (good, bad)).reshape(-1)
    states = np.tile([start_bad, not start_bad], pairs)
    flags = np.repeat(states, runs)
    while flags.size < n:  # rare: not enough runs drawn
        flags = np.concatenate((flags, _gilbert_runs(loss, burst_len, n - flags.size, rng)))
    return flags[:n]


def _outage_windows_s(direction: DirectionProfile, horizon_s: float, rng: np.random.Generator) -> list[tuple[float, float]]:
    """Scheduled windows plus an independently drawn on/off process up to ``horizon_s``."""
    spec = direction.outage
    windows = list(spec.windows_s)
    if spec.mean_interval_s is not None:
        t_s = 0.0
        while t_s <= horizon_s:
            start_s = t_s + rng.exponential(spec.mean_interval_s)
            t_s = start_s + rng.uniform(*spec.duration_s)
            windows.append((start_s, t_s))
    return _union(windows)


def _union(windows: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Overlapping windows merged, sorted."""
    return list(zip(*merge_windows(windows))) if windows else []


def _in_windows(t_s: np.ndarray, windows: list[tuple[float, float]]) -> np.ndarray:
    if not windows:
        return np.zeros(t_s.shape, dtype=bool)
    starts, ends = (np.array(x) for x in zip(*windows))
    index = np.searchsorted(starts, t_s, side="right") - 1
    return (index >= 0) & (t_s < ends[np.maximum(index, 0)])


def declared(
    direction: DirectionProfile, settings: Settings, law: DelayLaw | None = None
) -> tuple[Summary, dict[str, str]]:
    """The profile's declared Summary and, per quantity, how it was obtained (``law``: its delay law, if known)."""
    law = law or declared_law(direction, settings)
    stats = {k: float(law.quantile_ms(q)) for k, q in QUANTILES.items()}
    loss, burst, burst_method = declared_loss(direction, settings)
    methods = {"delay": law.method, "loss_ratio": "analytic", "mean_burst_len": burst_method}
    return Summary(law.mean_ms, **stats, loss_ratio=loss, mean_burst_len=burst), methods


# ---- the report ----------------------------------------------------------------------------


def reference_delays_ms(direction: DirectionProfile, settings: Settings) -> np.ndarray | None:
    """The measured delays a trace-based direction should reproduce (ms), else None."""
    s_ms = serialization_ms(direction, settings.size_bytes)
    if direction.replay is not None:
        return direction.delay_ms + trace_delays_ms(direction) + s_ms
    jitter = direction.jitter
    if jitter.distribution == "empirical" and jitter.trace is not None and direction.spikes is None:
        return np.maximum(0.0, direction.delay_ms + load_trace(jitter.trace).delay_ms) + s_ms
    return None


def effective_samples(direction: DirectionProfile, delivered: int) -> float:
    """How many independent draws ``delivered`` delays are worth for a quantile.

    AR(1) scores with lag-1 correlation rho: the indicators 1{z_k <= c} have lag-j correlation
    (2/pi) asin(rho^j) <= rho^j, so the variance of their mean is at most (1 + rho) / (1 - rho)
    times the i.i.d. one: n_eff = n (1 - rho) / (1 + rho). A replay holds no more than its
    trace's rows.
    """
    rho = direction.correlation if direction.jitter.distribution != "none" else 0.0
    n_eff = delivered * (1.0 - rho) / (1.0 + rho)
    if direction.replay is not None:
        n_eff = min(n_eff, float(load_trace(direction.replay.trace).delay_ms.size))
    return n_eff


def p50_range_ms(law: DelayLaw, n_eff: float, p: float = 0.5) -> tuple[float, float]:
    """Where the achieved p-quantile of ``n_eff`` draws from ``law`` lies (ms): [Q(p - d), Q(p + d)].

    The sample p-quantile X of n i.i.d. draws from F has F(X) ~ Beta(k, n + 1 - k), k = ceil(n p):
    mean ~ p, sd sqrt(p (1 - p) / n) (order statistics; for a smooth F it is the asymptotic sd
    sqrt(p (1 - p) / n) / f(Q(p)) of the quantile, but it needs no density and holds for
    discrete laws such as a trace). A Monte Carlo law is itself a sample quantile of
    ``law.draws`` draws, so the variances add: d = Z sqrt(p (1 - p) (1 / n_eff + 1 / draws)),
    Z = ``P50_Z``. Heavy tails (small f(Q(p))) and few samples widen the range in ms.
    """
    if n_eff <= 0.0:
        return -math.inf, math.inf
    d = P50_Z * math.sqrt(p * (1.0 - p) * (1.0 / n_eff + 1.0 / law.draws))
    low, high = law.quantile_ms(np.array([max(p - d, 0.0), min(p + d, 1.0)]))
    return float(low), float(high)


def keeps_order(direction: DirectionProfile) -> bool:
    """Whether the channel promises never to reorder: a replay of a trace that never reorders, plus a constant."""
    if direction.replay is None or direction.spikes is not None or direction.jitter.distribution != "none":
        return False
    return load_trace(direction.replay.trace).overtaken_ratio == 0.0


def checks(declared_s: Summary, achieved_s: Summary, p50_range: tuple[float, float], trace: bool) -> dict[str, bool]:
    """The acceptance criteria on delays and losses, each True when met."""
    out = {
        "loss_ratio_within_10pct": abs(achieved_s.loss_ratio - declared_s.loss_ratio)
        <= LOSS_RTOL * declared_s.loss_ratio + 1e-12,
        "p50_within_sampling_error": (achieved_s.p50_ms is None) == (declared_s.p50_ms is None)
        and (achieved_s.p50_ms is None or p50_range[0] <= achieved_s.p50_ms <= p50_range[1]),
    }
    if trace:
        out["p99_within_3ms_of_trace"] = _close(achieved_s.p99_ms, declared_s.p99_ms, TRACE_P99_ATOL_MS)
    return out


def _close(a: float | None, b: float | None, atol: float) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return abs(a - b) <= atol


def validate_direction(name: str, direction_name: str, direction: DirectionProfile, settings: Settings) -> dict:
    """The validation report of one direction (JSON-ready)."""
    delays_ms, lost = achieved(direction, settings, direction_name)
    achieved_s = summarise(delays_ms, lost)
    law = declared_law(direction, settings)
    declared_s, methods = declared(direction, settings, law)
    n_eff = effective_samples(direction, delays_ms.size)
    p50_range = p50_range_ms(law, n_eff)
    report = {
        "profile": name,
        "direction": direction_name,
        "samples": settings.samples,
        "seed": settings.seed,
        "interval_ms": settings.interval_ms,
        "size_bytes": settings.size_bytes,
        "distance_m": settings.distance_m,
        "declared": declared_s.as_dict(),
        "declared_method": methods,
        "achieved": achieved_s.as_dict(),
        "effective_samples": n_eff,
        "p50_range_ms": [v if math.isfinite(v) else None for v in p50_range],
        "overtaken_ratio": overtaken_ratio(_arrivals_ns(delays_ms, lost, settings)),
    }
    reference = reference_delays_ms(direction, settings)
    if reference is not None:
        from scipy.stats import ks_2samp  # (here: scipy.stats takes ~0.4 s to import, the link's start-up need not)

        report["ks_statistic"] = float(ks_2samp(delays_ms, reference).statistic) if delays_ms.size else None
    report["checks"] = checks(declared_s, achieved_s, p50_range, trace=direction.replay is not None)
    if keeps_order(direction):
        report["checks"]["replay_keeps_order"] = report["overtaken_ratio"] == 0.0
    report["pass"] = all(report["checks"].values())
    return report


def _arrivals_ns(delays_ms: np.ndarray, lost: np.ndarray, settings: Settings) -> np.ndarray:
    """Arrival times (int ns after the first send) of the delivered messages, in send order."""
    send_ns = np.flatnonzero(~lost) * round(settings.interval_ms * NS_PER_MS)
    return send_ns + np.rint(delays_ms * NS_PER_MS).astype(np.int64)
