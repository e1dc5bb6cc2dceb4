"""Link profiles: per-direction delay, jitter and loss, declared as YAML data.

A message's one-way delay is ``D = max(0, delay_ms + J)`` with ``J`` drawn from the
direction's jitter distribution, independently per message; it is lost with probability
``loss_probability`` (Bernoulli, independent per message). All times are milliseconds.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator
from scipy.stats import norm

from schemas.config import ConfigError, bundled_names, load_bundled_or_file

_PROFILE_DIR = "profiles"  # data folder inside the link_emulator package
_STRICT = ConfigDict(frozen=True, extra="forbid")


class ProfileError(ConfigError):
    """A link profile that cannot be found or read; the message names the bad field."""


class DelaySummary(NamedTuple):
    """Declared one-way delay of a direction, after clipping at 0 (milliseconds)."""

    median_ms: float
    mean_ms: float


class NoJitter(BaseModel):
    """J = 0: the delay is exactly the base delay."""

    model_config = _STRICT
    distribution: Literal["none"] = "none"

    def draw_ms(self, rng: np.random.Generator) -> float:
        """One jitter sample in ms (always 0)."""
        return 0.0

    def summary_ms(self, base_ms: float) -> DelaySummary:
        """Median and mean of max(0, base_ms + J) in ms."""
        return DelaySummary(base_ms, base_ms)


class NormalJitter(BaseModel):
    """J ~ N(mean_ms, std_ms^2); the resulting delay is clipped at 0."""

    model_config = _STRICT
    distribution: Literal["normal"]
    mean_ms: float = 0.0
    std_ms: float = Field(ge=0.0)

    def draw_ms(self, rng: np.random.Generator) -> float:
        """One jitter sample in ms."""
        return float(rng.normal(self.mean_ms, self.std_ms))

    def summary_ms(self, base_ms: float) -> DelaySummary:
        """Median and mean of max(0, X), X ~ N(mu, s^2), mu = base_ms + mean_ms (ms)."""
        mu, s = base_ms + self.mean_ms, self.std_ms
        if s == 0.0:
            return DelaySummary(max(0.0, mu), max(0.0, mu))
        # E[max(0, X)] = mu * Phi(mu / s) + s * phi(mu / s)  (mean of a normal clipped at 0)
        z = mu / s
        return DelaySummary(max(0.0, mu), float(mu * norm.cdf(z) + s * norm.pdf(z)))


class UniformJitter(BaseModel):
    """J ~ U(low_ms, high_ms); the resulting delay is clipped at 0."""

    model_config = _STRICT
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

    def draw_ms(self, rng: np.random.Generator) -> float:
        """One jitter sample in ms."""
        return float(rng.uniform(self.low_ms, self.high_ms))

    def summary_ms(self, base_ms: float) -> DelaySummary:
        """Median and mean of max(0, X), X ~ U(a, b), a = base + low, b = base + high (ms)."""
        a, b = base_ms + self.low_ms, base_ms + self.high_ms
        median_ms = max(0.0, 0.5 * (a + b))
        if a >= 0.0:
            return DelaySummary(median_ms, 0.5 * (a + b))
        if b <= 0.0:
            return DelaySummary(0.0, 0.0)
        # E[max(0, X)] = integral_0^b x dx / (b - a) = b^2 / (2 (b - a))
        return DelaySummary(median_ms, b * b / (2.0 * (b - a)))


class ExponentialJitter(BaseModel):
    """J ~ Exp(mean scale_ms): non-negative, models MAC back-off and queueing."""

    model_config = _STRICT
    distribution: Literal["exponential"]
    scale_ms: float = Field(gt=0.0)

    def draw_ms(self, rng: np.random.Generator) -> float:
        """One jitter sample in ms."""
        return float(rng.exponential(self.scale_ms))

    def summary_ms(self, base_ms: float) -> DelaySummary:
        """Median base + scale ln 2 and mean base + scale (ms); J >= 0 so no clipping."""
        return DelaySummary(base_ms + self.scale_ms * math.log(2.0), base_ms + self.scale_ms)


class LognormalJitter(BaseModel):
    """J = median_ms * exp(sigma * Z), Z ~ N(0, 1): heavy right tail (occasional spikes).

    ``sigma`` is the dimensionless standard deviation of ln J.
    """

    model_config = _STRICT
    distribution: Literal["lognormal"]
    median_ms: float = Field(gt=0.0)
    sigma: float = Field(ge=0.0)

    def draw_ms(self, rng: np.random.Generator) -> float:
        """One jitter sample in ms."""
        return float(rng.lognormal(math.log(self.median_ms), self.sigma))

    def summary_ms(self, base_ms: float) -> DelaySummary:
        """Median base + median_ms, mean base + median_ms exp(sigma^2 / 2) (ms); J > 0."""
        return DelaySummary(base_ms + self.median_ms, base_ms + self.median_ms * math.exp(0.5 * self.sigma**2))


Jitter = Annotated[
    NoJitter | NormalJitter | UniformJitter | ExponentialJitter | LognormalJitter,
    Field(discriminator="distribution"),
]


class DirectionProfile(BaseModel):
    """One direction of the link: base delay (ms) + jitter (ms), clipped at 0, and loss."""

    model_config = _STRICT
    delay_ms: float = Field(ge=0.0, description="base one-way delay in ms")
    jitter: Jitter = Field(default_factory=NoJitter, description="added to delay_ms per message")
    loss_probability: float = Field(default=0.0, ge=0.0, le=1.0, description="Bernoulli loss per message")

    def declared_delay_ms(self) -> DelaySummary:
        """Median and mean of the declared one-way delay (ms) of delivered messages."""
        return self.jitter.summary_ms(self.delay_ms)


class LinkProfile(BaseModel):
    """A named link: uplink (vehicle -> RSU) and downlink (RSU -> vehicle) directions."""

    model_config = _STRICT
    name: str = Field(min_length=1)
    description: str = ""
    uplink: DirectionProfile
    downlink: DirectionProfile


def bundled_profiles() -> list[str]:
    """Names of the profiles shipped in ``link_emulator/profiles/*.yaml``, sorted."""
    return bundled_names("link_emulator", _PROFILE_DIR)


def load_profile(name_or_path: str | Path) -> LinkProfile:
    """A bundled profile by name (e.g. ``"lte-v2x"``) or a profile YAML file by path.

    Raises ProfileError listing the bundled names when neither exists, or naming the bad
    field when the YAML does not validate.
    """
    return load_bundled_or_file(LinkProfile, name_or_path, "link_emulator", _PROFILE_DIR, "link profile", ProfileError)
