"""Link profiles: what each direction of a link does to a message, declared as YAML data.

Per direction (all optional except ``delay_ms``; a new profile needs no code):

- delay ``D = max(0, delay_ms + J [+ spike] [+ trace delay])`` ms, ``J`` from ``jitter``
  (none, normal, uniform, exponential, lognormal, pareto, empirical), optionally correlated
  from message to message (``correlation``, see ``channel.py`` for the AR(1) equation);
- loss: Bernoulli with ``loss_probability``, or Gilbert-Elliott bursts with the same mean
  rate and ``mean_burst_len``; times the packet delivery ratio at the message's distance
  (``pdr_curve``), nothing beyond ``range_m``; scheduled or random ``outage`` windows;
- ``bandwidth_kbps`` (serialization ``8 size / rate`` and a FIFO send queue), ``fifo``
  delivery order, ``duplicate_probability``, and ``replay`` of a measured delay trace.

All times are milliseconds unless a name says otherwise.
"""

from __future__ import annotations

import math
from itertools import pairwise
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from v2i.core.files import MiB
from v2i.runtime.config import ConfigError, bundled_names, load_bundled_or_file

from link_emulator.distributions import (  # re-exported: the jitter models are part of a profile
    DelaySummary,
    EmpiricalJitter,
    ExponentialJitter,
    Jitter,
    LognormalJitter,
    NoJitter,
    NormalJitter,
    ParetoJitter,
    UniformJitter,
)
from link_emulator.trace import load_trace

__all__ = [
    "DelaySummary", "DirectionProfile", "EmpiricalJitter", "ExponentialJitter", "Jitter", "LinkProfile",
    "LognormalJitter", "NoJitter", "NormalJitter", "OutageSpec", "ParetoJitter", "ProfileError", "SpikeSpec",
    "TraceReplay", "UniformJitter", "bundled_profiles", "load_profile",
]

PROFILE_LIMIT_BYTES = 1 * MiB  # a link profile: a few dozen fields (a trace is a file of its own)
_PROFILE_DIR = "profiles"  # data folder inside the link_emulator package
_STRICT = ConfigDict(frozen=True, extra="forbid")


class ProfileError(ConfigError):
    """A link profile that cannot be found or read; the message names the bad field."""


class SpikeSpec(BaseModel):
    """With ``probability`` per message, an extra delay drawn from ``extra`` (ms) is added."""

    model_config = _STRICT
    probability: float = Field(ge=0.0, le=1.0)
    extra: Jitter


class OutageSpec(BaseModel):
    """Windows during which the link is down, measured from the channel's first message.

    ``windows_s``: scheduled ``[start_s, end_s]`` pairs. ``mean_interval_s`` and
    ``duration_s``: a random on/off process, up time ~ Exp(mean_interval_s) and outage
    duration ~ U(duration_s[0], duration_s[1]); its long-run down fraction is
    E[down] / (mean_interval_s + E[down]). ``mode``: ``drop`` loses what is sent while down;
    ``hold`` buffers it and sends it when the link is back (e.g. a handover with forwarding).
    """

    model_config = _STRICT
    mode: Literal["drop", "hold"] = "drop"
    windows_s: list[tuple[float, float]] = Field(default_factory=list)
    mean_interval_s: float | None = Field(default=None, gt=0.0)
    duration_s: tuple[float, float] | None = None

    @field_validator("windows_s")
    @classmethod
    def _windows_ordered(cls, windows: list[tuple[float, float]]) -> list[tuple[float, float]]:
        for start_s, end_s in windows:
            if not 0.0 <= start_s < end_s:
                raise ValueError(f"each window needs 0 <= start_s < end_s, got [{start_s}, {end_s}]")
        return sorted(windows)

    @field_validator("duration_s")
    @classmethod
    def _duration_range(cls, duration: tuple[float, float] | None) -> tuple[float, float] | None:
        if duration is not None and not 0.0 < duration[0] <= duration[1]:
            raise ValueError(f"needs 0 < low <= high, got {list(duration)}")
        return duration

    @model_validator(mode="after")
    def _random_needs_both(self) -> OutageSpec:
        if (self.mean_interval_s is None) != (self.duration_s is None):
            raise ValueError("mean_interval_s and duration_s go together (a random outage process)")
        return self

    def random_down_fraction(self) -> float:
        """Long-run fraction of time the random process is down (0 without one)."""
        if self.duration_s is None or self.mean_interval_s is None:
            return 0.0
        mean_down_s = 0.5 * (self.duration_s[0] + self.duration_s[1])
        return mean_down_s / (self.mean_interval_s + mean_down_s)


class TraceReplay(BaseModel):
    """Replay a CICV5G-format trace in time, on its own send times, looped from a seeded phase.

    A message entering the network ``t`` ms after the channel's first one takes the delay of
    the nearer trace row in time, with falls drained in FIFO order, so the replay keeps the
    trace's order and never leaves its neighbouring rows' delays (``processes.TraceClock``);
    the delay is added to ``delay_ms``. A send time inside a gap of the trace loses the message.
    """

    model_config = _STRICT
    trace: str = Field(min_length=1, description="bundled trace name (see trace.bundled_traces) or a file path "
                                                 "(relative to the working directory); .gz is decompressed")

    @field_validator("trace")
    @classmethod
    def _trace_is_readable(cls, trace: str) -> str:
        load_trace(trace)  # TraceError (a ValueError) names the file and the line
        return trace


class DirectionProfile(BaseModel):
    """One direction of the link; see the module docstring for the model."""

    model_config = _STRICT
    delay_ms: float = Field(ge=0.0, description="base one-way delay in ms")
    jitter: Jitter = Field(default_factory=NoJitter, description="added to delay_ms per message")
    correlation: float = Field(default=0.0, ge=0.0, lt=1.0, description="lag-1 correlation of the jitter's normal score")
    spikes: SpikeSpec | None = None
    loss_probability: float = Field(default=0.0, ge=0.0, le=1.0, description="mean loss rate per message")
    mean_burst_len: float | None = Field(
        default=None, ge=1.0,
        description="Gilbert-Elliott mean loss-burst length in messages (omit: Bernoulli); "
                    "values below Bernoulli's 1 / (1 - loss_probability) act as Bernoulli")
    pdr_curve: list[tuple[float, float]] | None = Field(
        default=None, min_length=1,
        description="[distance_m, pdr] points, linearly interpolated, held at the ends; the delivery ratio at a "
                    "known distance is pdr(d) * (1 - loss_probability)")
    range_m: float | None = Field(
        default=None, gt=0.0,
        description="beyond this distance everything is lost (Saravanan et al.: the RSU reaches 80 m)")
    outage: OutageSpec | None = None
    bandwidth_kbps: float | None = Field(default=None, gt=0.0, description="send rate in kbit/s (1000 bit/s)")
    queue_limit_ms: float | None = Field(default=None, ge=0.0, description="longest wait in the send queue; tail drop")
    fifo: bool = Field(default=False, description="never deliver a message before an earlier one")
    duplicate_probability: float = Field(default=0.0, ge=0.0, le=1.0)
    replay: TraceReplay | None = None

    @field_validator("pdr_curve")
    @classmethod
    def _curve_is_valid(cls, curve: list[tuple[float, float]] | None) -> list[tuple[float, float]] | None:
        if curve is None:
            return None
        distances = [d for d, _ in curve]
        if distances[0] < 0.0 or any(b <= a for a, b in pairwise(distances)):
            raise ValueError("distances must be >= 0 and strictly increasing")
        if any(not 0.0 <= p <= 1.0 for _, p in curve):
            raise ValueError("each pdr must be in [0, 1]")
        return curve

    @model_validator(mode="after")
    def _queue_limit_needs_bandwidth(self) -> DirectionProfile:
        if self.queue_limit_ms is not None and self.bandwidth_kbps is None:
            raise ValueError("queue_limit_ms needs bandwidth_kbps (there is no queue without a rate)")
        return self

    def declared_delay_ms(self) -> DelaySummary:
        """Median and mean of max(0, delay_ms + J) in ms: the jitter alone (no spikes, trace, queue)."""
        return self.jitter.summary_ms(self.delay_ms)

    def pdr_at(self, distance_m: np.ndarray | float) -> np.ndarray:
        """Delivery ratio at ``distance_m``: the curve (1 without one), 0 beyond ``range_m``."""
        d = np.asarray(distance_m, dtype=float)
        pdr = np.ones_like(d) if self.pdr_curve is None else np.interp(d, *zip(*self.pdr_curve))
        return np.where(d > (self.range_m if self.range_m is not None else math.inf), 0.0, pdr)


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
    return load_bundled_or_file(LinkProfile, name_or_path, "link_emulator", _PROFILE_DIR, "link profile", ProfileError,
                                limit_bytes=PROFILE_LIMIT_BYTES)
