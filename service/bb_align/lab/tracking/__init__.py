"""Tracking through time, measured: replay sequences through the engine's follower (`bb-align track`)."""
