"""Jitter distributions of a link direction, declared as YAML data.

Every distribution is written as a transform of a standard normal variate: ``J = g(z)``
with ``g(z) = F^-1(Phi(z))`` (``F`` the distribution's CDF, ``Phi`` the standard normal
CDF). A channel draws ``z`` (independent, or AR(1)-correlated: see ``channel.py``) and maps
it through ``g``; because ``Phi(z)`` is uniform for any standard normal ``z``, the jitter
has exactly the declared distribution whatever the correlation. The same ``g`` gives the
declared quantiles analytically: ``Q(q) = g(Phi^-1(q))``.

All values are milliseconds; the one-way delay is ``D = max(0, base_ms + J)``.
"""

from __future__ import annotations

import math
from functools import cached_property
from typing import Annotated, Literal, NamedTuple

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)
from scipy.special import log_ndtr, ndtr, ndtri

from link_emulator.trace import load_trace


def _normal_pdf(z: float) -> float:
    """phi(z) = exp(-z^2 / 2) / sqrt(2 pi), as scipy.stats.norm.pdf computes it (scipy.stats itself
    takes ~0.4 s to import, in every link emulator and evaluator process)."""
    return np.exp(-z**2 / 2.0) / np.sqrt(2 * np.pi)

_STRICT = ConfigDict(frozen=True, extra="forbid")


class DelaySummary(NamedTuple):
    """Declared one-way delay of a direction, after clipping at 0 (milliseconds)."""

    median_ms: float
    mean_ms: float


class _Jitter(BaseModel):
    model_config = _STRICT

    def from_normal(self, z: np.ndarray) -> np.ndarray:
        """Jitter in ms, ``g(z) = F^-1(Phi(z))``, elementwise; ``z`` standard normal, any shape."""
        raise NotImplementedError

    def mean_clipped_ms(self, base_ms: float) -> float:
        """E[max(0, base_ms + J)] in ms."""
        raise NotImplementedError

    def quantile_ms(self, base_ms: float, q: float) -> float:
        """q-quantile of max(0, base_ms + J) in ms (clipping is monotone, so it commutes)."""
        return max(0.0, base_ms + float(self.from_normal(np.array(ndtri(q)))))  # ndtri: the normal quantile

    def summary_ms(self, base_ms: float) -> DelaySummary:
        """Median and mean of max(0, base_ms + J) in ms."""
        return DelaySummary(self.quantile_ms(base_ms, 0.5), self.mean_clipped_ms(base_ms))

    def draw_ms(self, rng: np.random.Generator) -> float:
        """One independent jitter sample in ms."""
        return float(self.from_normal(np.array(rng.standard_normal())))


class NoJitter(_Jitter):
    """J = 0: the delay is exactly the base delay."""

    distribution: Literal["none"] = "none"

    def from_normal(self, z: np.ndarray) -> np.ndarray:
        return np.zeros_like(z, dtype=float)

    def mean_clipped_ms(self, base_ms: float) -> float:
        return max(0.0, base_ms)


class NormalJitter(_Jitter):
    """J ~ N(mean_ms, std_ms^2); the resulting delay is clipped at 0."""

    distribution: Literal["normal"]
    mean_ms: float = 0.0
    std_ms: float = Field(ge=0.0)

    def from_normal(self, z: np.ndarray) -> np.ndarray:
        return self.mean_ms + self.std_ms * z

    def mean_clipped_ms(self, base_ms: float) -> float:
        mu, s = base_ms + self.mean_ms, self.std_ms
        if s == 0.0:
            return max(0.0, mu)
        # E[max(0, X)] = mu * Phi(mu / s) + s * phi(mu / s)  (mean of a normal clipped at 0)
        z = mu / s
        return float(mu * ndtr(z) + s * _normal_pdf(z))


class UniformJitter(_Jitter):
    """J ~ U(low_ms, high_ms); the resulting delay is clipped at 0."""

    distribution: Literal["uniform"]
    low_ms: float
    high_ms: float

    @field_validator("high_ms")
    @classmethod
    def _high_not_below_low(cls, high_ms: float, info: ValidationInfo) -> float:
        low_ms = info.data.get("low_ms")
        if low_ms is not None and high_ms < low_ms:
            raise ValueError(f"must be >= low_ms ({low_ms})")
        return high_ms

    def from_normal(self, z: np.ndarray) -> np.ndarray:
        # J = a + (b - a) Phi(z)
        return self.low_ms + (self.high_ms - self.low_ms) * ndtr(z)

    def mean_clipped_ms(self, base_ms: float) -> float:
        a, b = base_ms + self.low_ms, base_ms + self.high_ms
        if a >= 0.0:
            return 0.5 * (a + b)
        if b <= 0.0:
            return 0.0
        # E[max(0, X)] = integral_0^b x dx / (b - a) = b^2 / (2 (b - a))
        return b * b / (2.0 * (b - a))


class ExponentialJitter(_Jitter):
    """J ~ Exp(mean scale_ms): non-negative, models MAC back-off and queueing."""

    distribution: Literal["exponential"]
    scale_ms: float = Field(gt=0.0)

    def from_normal(self, z: np.ndarray) -> np.ndarray:
        # J = -scale ln(1 - Phi(z)) = -scale ln Phi(-z)  (log_ndtr keeps the far tail exact)
        return -self.scale_ms * log_ndtr(-z)

    def mean_clipped_ms(self, base_ms: float) -> float:
        return base_ms + self.scale_ms  # J >= 0 and base >= 0: no clipping


class LognormalJitter(_Jitter):
    """J = median_ms * exp(sigma * Z), Z ~ N(0, 1): heavy right tail (occasional spikes).

    ``sigma`` is the dimensionless standard deviation of ln J.
    """

    distribution: Literal["lognormal"]
    median_ms: float = Field(gt=0.0)
    sigma: float = Field(ge=0.0)

    def from_normal(self, z: np.ndarray) -> np.ndarray:
        return self.median_ms * np.exp(self.sigma * z)

    def mean_clipped_ms(self, base_ms: float) -> float:
        # E[J] = median exp(sigma^2 / 2); J > 0 so no clipping for base >= 0
        return base_ms + self.median_ms * math.exp(0.5 * self.sigma**2)


class ParetoJitter(_Jitter):
    """Pareto type II (Lomax), as numpy's ``Generator.pareto``: J = scale_ms ((1 - U)^(-1/shape) - 1).

    J >= 0 with a power-law tail P(J > x) = (1 + x / scale_ms)^-shape; the mean is finite
    only for shape > 1 (scale_ms / (shape - 1)).
    """

    distribution: Literal["pareto"]
    scale_ms: float = Field(gt=0.0)
    shape: float = Field(gt=0.0)

    def from_normal(self, z: np.ndarray) -> np.ndarray:
        # 1 - U = Phi(-z): J = scale (exp(-ln Phi(-z) / shape) - 1)
        return self.scale_ms * np.expm1(-log_ndtr(-z) / self.shape)

    def mean_clipped_ms(self, base_ms: float) -> float:
        if self.shape <= 1.0:
            return math.inf
        return base_ms + self.scale_ms / (self.shape - 1.0)


class EmpiricalJitter(_Jitter):
    """J drawn from measured samples: the inverse empirical CDF, J = x_(floor(n Phi(z))).

    Give either ``samples_ms`` inline or ``trace``: a CICV5G-format delay trace (a bundled
    name such as ``cicv5g/urban_n78_v20_run01.txt.gz`` or a file path) whose delay column
    is used. Values are taken as they are (no interpolation), so a replay keeps the trace's
    resolution and a two-sample KS test against the trace goes to 0.
    """

    distribution: Literal["empirical"]
    samples_ms: list[float] | None = Field(default=None, min_length=1)
    trace: str | None = None

    @field_validator("trace")
    @classmethod
    def _trace_is_readable(cls, trace: str | None) -> str | None:
        if trace is not None:
            load_trace(trace)  # raises TraceError (a ValueError) naming the file and line
        return trace

    @model_validator(mode="after")
    def _one_source(self) -> EmpiricalJitter:
        if (self.samples_ms is None) == (self.trace is None):
            raise ValueError("give exactly one of samples_ms and trace")
        return self

    @cached_property
    def sorted_ms(self) -> np.ndarray:
        """The samples in ms, sorted ascending, shape (n,)."""
        values = np.asarray(self.samples_ms) if self.trace is None else load_trace(self.trace).delay_ms
        return np.sort(values.astype(float))

    def from_normal(self, z: np.ndarray) -> np.ndarray:
        x = self.sorted_ms
        index = np.minimum((ndtr(z) * x.size).astype(np.int64), x.size - 1)
        return x[index]

    def mean_clipped_ms(self, base_ms: float) -> float:
        return float(np.mean(np.maximum(0.0, base_ms + self.sorted_ms)))


Jitter = Annotated[
    NoJitter | NormalJitter | UniformJitter | ExponentialJitter | LognormalJitter | ParetoJitter | EmpiricalJitter,
    Field(discriminator="distribution"),
]
