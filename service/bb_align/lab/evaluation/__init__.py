"""Evaluation harness: run the engine over an OPV2V / V2V4Real-layout dataset and report the paper's metrics
(success rate, error CDFs, accuracy by distance / common cars / inliers, stage-1 ablation, a graph-matching
baseline, late-fusion detection AP with noisy / recovered / true pose).

The names below load on first use, so registering ``bb-align eval`` (and ``bb-align --help``) stays cheap."""

from importlib import import_module

_API = {
    "EvalConfig": ".runner",
    "PairRecord": ".runner",
    "evaluate_dataset": ".runner",
    "evaluate_group": ".runner",
    "summarize": ".summary",
}
__all__ = sorted(_API)


def __getattr__(name: str):
    if name in _API:
        return getattr(import_module(_API[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
