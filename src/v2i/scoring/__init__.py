"""Scoring fused outputs against ground truth: detection, tracking and consistency metrics (pure)."""

# the modules that declare the evaluation's compiled kernels: the matches per frame (v2i.core.jit)
KERNEL_MODULES = ("v2i.scoring.detection_metrics",)
