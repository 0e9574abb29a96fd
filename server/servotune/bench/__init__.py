"""The tuning test bench: tests, runs, metrics, quality, import and export."""
