"""Chaos timelines: timed faults for a live demo (``v2i chaos run``) or an offline run
(``v2i eval --chaos``). Pure: a YAML file becomes a validated, time-ordered list of events.

    name: tunnel
    events:
      - {at_s: 8, outage: {duration_s: 10}}                        # link down both ways
      - {at_s: 2, profile: dsrc}                                   # switch the link profile
      - {at_s: 4, delay_spike: {duration_s: 2, extra_ms: 300, direction: downlink}}
      - {at_s: 5, loss_burst: {duration_s: 1, loss_probability: 0.5}}
      - {at_s: 6, bandwidth_cap: {duration_s: 3, kbps: 64}}
      - {at_s: 15, rsu_clock_step: {step_ms: 500}}                 # at most one per timeline
      - {at_s: 20, kill: link}                                     # SIGKILL the service ...
      - {at_s: 23, restart: link}                                  # ... and start it again

Times are scenario seconds. Link events become ``LinkControl`` messages, applied by the
same ``link_emulator.control.apply_control`` live and offline.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from v2i.core.files import MiB
from v2i.runtime.config import ConfigError, read_yaml, validate
from schemas.messages import LinkControl

from v2i.offline.spec import RunSpec

SERVICES = ("link", "rsu")  # what a timeline may kill and restart (the OBU is the system under test)
Direction = Literal["uplink", "downlink", "both"]
CHAOS_LIMIT_BYTES = 1 * MiB  # a timeline: tens of steps, a few kB
_STRICT = ConfigDict(frozen=True, extra="forbid")


class ChaosError(ConfigError):
    """A chaos timeline that cannot be read; the message names the file and the bad field."""


class Outage(BaseModel):
    model_config = _STRICT
    duration_s: float = Field(gt=0)
    direction: Direction = "both"


class DelaySpike(BaseModel):
    model_config = _STRICT
    duration_s: float = Field(gt=0)
    extra_ms: float = Field(gt=0, le=600_000)
    direction: Direction = "both"


class LossBurst(BaseModel):
    model_config = _STRICT
    duration_s: float = Field(gt=0)
    loss_probability: float = Field(ge=0, le=1)
    direction: Direction = "both"


class BandwidthCap(BaseModel):
    model_config = _STRICT
    duration_s: float = Field(gt=0)
    kbps: float = Field(gt=0)
    direction: Direction = "both"


class ClockStep(BaseModel):
    model_config = _STRICT
    step_ms: float = Field(ge=-86_400_000, le=86_400_000)


class ChaosEvent(BaseModel):
    """One fault at ``at_s``: exactly one of the action fields."""

    model_config = _STRICT
    at_s: float = Field(ge=0)
    profile: str | None = None
    outage: Outage | None = None
    delay_spike: DelaySpike | None = None
    loss_burst: LossBurst | None = None
    bandwidth_cap: BandwidthCap | None = None
    rsu_clock_step: ClockStep | None = None
    kill: Literal["link", "rsu"] | None = None
    restart: Literal["link", "rsu"] | None = None

    @model_validator(mode="after")
    def _one_action(self) -> "ChaosEvent":
        actions = [n for n in ChaosEvent.model_fields if n != "at_s" and getattr(self, n) is not None]
        if len(actions) != 1:
            raise ValueError(f"an event has exactly one action, got {actions or 'none'}")
        return self

    def link_control(self, link_id: str) -> LinkControl | None:
        """The LinkControl message of a link event; None for service and clock events."""
        if self.profile is not None:
            return LinkControl(link_id=link_id, profile=self.profile)
        if self.outage:
            return LinkControl(link_id=link_id, duration_s=self.outage.duration_s, direction=self.outage.direction,
                               outage=True)
        if self.delay_spike:
            d = self.delay_spike
            return LinkControl(link_id=link_id, duration_s=d.duration_s, direction=d.direction, extra_delay_ms=d.extra_ms)
        if self.loss_burst:
            b = self.loss_burst
            return LinkControl(link_id=link_id, duration_s=b.duration_s, direction=b.direction,
                               loss_probability=b.loss_probability)
        if self.bandwidth_cap:
            c = self.bandwidth_cap
            return LinkControl(link_id=link_id, duration_s=c.duration_s, direction=c.direction, bandwidth_kbps=c.kbps)
        return None

    def describe(self) -> str:
        """One line naming the event's action."""
        if self.profile is not None:
            return f"profile {self.profile}"
        if self.kill or self.restart:
            return f"kill {self.kill}" if self.kill else f"restart {self.restart}"
        if self.rsu_clock_step:
            return f"RSU clock step {self.rsu_clock_step.step_ms:g} ms"
        name, fault = next((n, getattr(self, n)) for n in ("outage", "delay_spike", "loss_burst", "bandwidth_cap")
                           if getattr(self, n) is not None)
        details = {"delay_spike": lambda f: f" +{f.extra_ms:g} ms", "loss_burst": lambda f: f" loss {f.loss_probability:g}",
                   "bandwidth_cap": lambda f: f" {f.kbps:g} kbit/s"}.get(name, lambda f: "")(fault)
        return f"{name}{details} on {fault.direction} for {fault.duration_s:g} s"


class ChaosTimeline(BaseModel):
    model_config = _STRICT
    name: str = Field(min_length=1)
    description: str = ""
    events: list[ChaosEvent] = Field(min_length=1)

    @model_validator(mode="after")
    def _consistent(self) -> "ChaosTimeline":
        if sum(e.rsu_clock_step is not None for e in self.events) > 1:
            raise ValueError("at most one rsu_clock_step per timeline")
        down: set[str] = set()
        for e in self.sorted_events():
            if e.kill:
                if e.kill in down:
                    raise ValueError(f"kill {e.kill} at {e.at_s} s: it is already down")
                down.add(e.kill)
            if e.restart:
                if e.restart not in down:
                    raise ValueError(f"restart {e.restart} at {e.at_s} s: it was not killed before")
                down.discard(e.restart)
        return self

    def sorted_events(self) -> list[ChaosEvent]:
        """Events by time; simultaneous ones in file order."""
        return sorted(self.events, key=lambda e: e.at_s)

    def clock_step(self) -> tuple[float, float] | None:
        """(at_s, step_ms) of the RSU clock step, if the timeline has one."""
        steps = [(e.at_s, e.rsu_clock_step.step_ms) for e in self.events if e.rsu_clock_step]
        return steps[0] if steps else None

    def fault_window_s(self, event: ChaosEvent, end_s: float) -> tuple[float, float] | None:
        """The scenario seconds a fault of this timeline lasts: an impairment's duration, a kill
        until its restart (or ``end_s``); None for instantaneous events (switch, step, restart)."""
        fault = event.outage or event.delay_spike or event.loss_burst or event.bandwidth_cap
        if fault is not None:
            return event.at_s, event.at_s + fault.duration_s
        if event.kill:
            return next(w for w in self.down_windows(event.kill, end_s) if w[0] == event.at_s)
        return None

    def down_windows(self, service: str, end_s: float) -> list[tuple[float, float]]:
        """[(kill_s, restart_s)] of a service; a service never restarted is down until ``end_s``."""
        windows, since = [], None
        for e in self.sorted_events():
            if e.kill == service:
                since = e.at_s
            elif e.restart == service and since is not None:
                windows.append((since, e.at_s))
                since = None
        return windows + ([(since, end_s)] if since is not None else [])


def load_chaos(path: str | Path) -> ChaosTimeline:
    """A validated timeline from a YAML file; ChaosError naming the file and field otherwise."""
    data = read_yaml(path, "chaos timeline", ChaosError, limit_bytes=CHAOS_LIMIT_BYTES)
    return validate(ChaosTimeline, data, f"chaos timeline {path}", ChaosError)


def with_chaos(spec: RunSpec, chaos: ChaosTimeline | None) -> RunSpec:
    """``spec`` with the timeline's RSU clock step (the RSU's clock is injected truth, set at start)."""
    step = chaos.clock_step() if chaos else None
    if step is None:
        return spec
    if spec.rsu_clock_step_at_s is not None:
        raise ChaosError("the chaos timeline has an rsu_clock_step and --rsu-clock-step-at-s is set too: use one")
    return replace(spec, rsu_clock_step_at_s=step[0], rsu_clock_step_ms=step[1])
