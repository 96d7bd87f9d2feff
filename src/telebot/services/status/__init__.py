"""Pose, goals and telemetry (part of every call's core)."""
