"""Scoring fused outputs against ground truth: detection, tracking and consistency metrics (pure)."""
