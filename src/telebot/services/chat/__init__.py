"""The ``chat`` channel's commands (part of every call's core)."""
