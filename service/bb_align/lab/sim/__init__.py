"""V2V LiDAR simulator: procedural streets, heterogeneous rotating LiDARs with self-motion distortion, and a
detector error model. ``simulate_sequence`` is the one-call entry point; ``writer`` saves OPV2V-style datasets."""

from .detections import DetectionModel, Detections, detect
from .scenario import Scenario, SimAgent, SimConfig, SimFrame, simulate_sequence
from .sensors import SENSOR_MODELS, SensorModel

__all__ = [
    "DetectionModel",
    "Detections",
    "SENSOR_MODELS",
    "Scenario",
    "SensorModel",
    "SimAgent",
    "SimConfig",
    "SimFrame",
    "detect",
    "simulate_sequence",
]
