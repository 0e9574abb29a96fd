"""The 3D twin of every axis (viser), embedded in the dashboard: see docs/twin.md."""
