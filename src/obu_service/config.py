"""OBU service configuration (YAML + CLI overrides, validated at start-up)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from schemas.config import ServiceConfig
from schemas.keys import check_id

from .methods import check_fusion
from .pipeline import COMPENSATIONS, FUSION_METHODS, FUSION_MODES, ObuPipelineConfig


class ObuConfig(ServiceConfig):
    vehicle_id: str = "ego"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7448"])
    fusion: Literal[FUSION_METHODS] = "kf"
    compensation: Literal[COMPENSATIONS] = "predict"
    fusion_mode: Literal[FUSION_MODES] = Field("adaptive", description="which RSU data a cycle fuses (seed 003)")
    iou_threshold: float = Field(0.1, gt=0, le=1)
    inter_max_age_s: float = Field(0.6, gt=0, le=30, description="inter-frame fusion uses RSU data up to this old")
    planning_max_age_s: float = Field(5.0, gt=0, le=60, description="planning fusion uses RSU paths up to this old")
    deadline_ms: float = Field(100.0, gt=0, le=10_000, description="end-to-end: own LiDAR capture -> fused output")
    output_interval_ms: float = Field(150.0, gt=0, le=10_000, description="longest allowed gap between two outputs")
    fuse_delay_ms: float = Field(50.0, ge=0, le=10_000, description="own perception latency: LiDAR capture -> fusion")
    sync_rate_hz: float = Field(10.0, gt=0, le=100)
    time_query_timeout_s: float = Field(2.0, gt=0, le=60)

    @field_validator("vehicle_id")
    @classmethod
    def _valid_id(cls, v: str) -> str:
        return check_id(v)

    @model_validator(mode="after")
    def _method_fits_compensation(self) -> "ObuConfig":
        check_fusion(self.fusion, self.compensation)
        return self

    @model_validator(mode="after")
    def _lane_needs_a_map(self) -> "ObuConfig":
        from pathlib import Path

        from sim.maps import bundled_maps, scenario_map

        if self.compensation == "lane" and scenario_map(self.scenario) is None:
            raise ValueError(
                f"compensation 'lane' needs a Lanelet2 map of scenario {self.scenario!r}, and "
                f"{Path(self.scenario).with_suffix('.osm')} does not exist (a <scenario>.osm beside the scenario "
                f"YAML is picked up automatically; bundled scenarios with maps: {', '.join(bundled_maps())})")
        return self

    def lanes(self):
        """The scenario's lane predictor when the ``lane`` compensation needs it, else None."""
        from sim.maps import lane_predictor

        return lane_predictor(self.scenario) if self.compensation == "lane" else None

    def pipeline_config(self) -> ObuPipelineConfig:
        return ObuPipelineConfig(
            vehicle_id=self.vehicle_id, fusion=self.fusion, compensation=self.compensation,
            fusion_mode=self.fusion_mode, iou_threshold=self.iou_threshold, inter_max_age_s=self.inter_max_age_s,
            planning_max_age_s=self.planning_max_age_s, deadline_ms=self.deadline_ms,
            output_interval_ms=self.output_interval_ms,
        )
