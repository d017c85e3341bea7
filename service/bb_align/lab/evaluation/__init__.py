"""Evaluation harness: run the engine over an OPV2V / V2V4Real-layout dataset and report the paper's metrics
(success rate, error CDFs, accuracy by distance / common cars / inliers, stage-1 ablation, a graph-matching
baseline, late-fusion detection AP with noisy / recovered / true pose)."""

from .runner import EvalConfig, PairRecord, evaluate_dataset, evaluate_group
from .summary import summarize

__all__ = ["EvalConfig", "PairRecord", "evaluate_dataset", "evaluate_group", "summarize"]
