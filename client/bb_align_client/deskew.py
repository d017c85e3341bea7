"""Undo a sweep's self-motion distortion before it is encoded (sender side): the engine's ``deskew_sweep`` (one
implementation for senders, ``bb-align eval``, ``track`` and ``recover``; the model is explained there)."""

from bb_align.engine.deskew import deskew_sweep, firing_times

__all__ = ["deskew_sweep", "firing_times"]
