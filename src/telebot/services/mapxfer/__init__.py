"""The map transfer (part of every call's core)."""
