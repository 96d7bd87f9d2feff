"""The safety channel and the robot's safety supervisor (part of every call's core)."""
