"""The 3D twin of every axis (viser), embedded in the dashboard: see docs/twin.md."""

from servotune.twin.service import Twin

__all__ = ["Twin"]
