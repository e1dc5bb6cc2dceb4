"""OBU service configuration (YAML + CLI overrides, validated at start-up)."""

from __future__ import annotations

from pydantic import Field, field_validator, model_validator

from schemas.config import ServiceConfig
from schemas.keys import check_id

from .pipeline import COMPENSATIONS, FUSION_METHODS, ObuPipelineConfig


class ObuConfig(ServiceConfig):
    vehicle_id: str = "ego"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7448"])
    fusion: str = "iou-merge"
    compensation: str = "predict"
    iou_threshold: float = Field(0.1, gt=0, le=1)
    max_rsu_age_s: float = Field(1.0, gt=0, le=30)
    deadline_ms: float = Field(100.0, gt=0, le=10_000)
    fuse_delay_ms: float = Field(50.0, ge=0, le=10_000, description="own perception latency: LiDAR capture -> fusion")
    sync_rate_hz: float = Field(2.0, gt=0, le=100)
    time_query_timeout_s: float = Field(2.0, gt=0, le=60)

    @field_validator("vehicle_id")
    @classmethod
    def _valid_id(cls, v: str) -> str:
        return check_id(v)

    @field_validator("fusion")
    @classmethod
    def _valid_fusion(cls, v: str) -> str:
        if v not in FUSION_METHODS:
            raise ValueError(f"must be one of {FUSION_METHODS}")
        return v

    @field_validator("compensation")
    @classmethod
    def _valid_compensation(cls, v: str) -> str:
        if v not in COMPENSATIONS:
            raise ValueError(f"must be one of {COMPENSATIONS}")
        return v

    @model_validator(mode="after")
    def _oosm_needs_kf(self) -> "ObuConfig":
        if self.compensation == "oosm" and not self.fusion.startswith("kf"):
            raise ValueError("compensation 'oosm' re-runs a filter: use it with fusion 'kf'")
        return self

    def pipeline_config(self) -> ObuPipelineConfig:
        return ObuPipelineConfig(
            vehicle_id=self.vehicle_id, fusion=self.fusion, compensation=self.compensation,
            iou_threshold=self.iou_threshold,
            max_rsu_age_s=self.max_rsu_age_s, deadline_ms=self.deadline_ms,
        )
