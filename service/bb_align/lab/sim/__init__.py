"""V2V LiDAR simulator: procedural streets, heterogeneous rotating LiDARs with self-motion distortion, and a
detector error model. ``simulate_sequence`` is the one-call entry point; ``writer`` saves OPV2V-style datasets.

The names below load on first use, so the CLI can read the sensor list without building the simulator."""

from importlib import import_module

_API = {
    "DetectionModel": ".detections",
    "Detections": ".detections",
    "detect": ".detections",
    "Scenario": ".scenario",
    "SimAgent": ".scenario",
    "SimConfig": ".scenario",
    "SimFrame": ".scenario",
    "simulate_sequence": ".scenario",
    "SENSOR_MODELS": ".sensors",
    "SensorModel": ".sensors",
}
__all__ = sorted(_API)


def __getattr__(name: str):
    if name in _API:
        return getattr(import_module(_API[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
