"""servotune: a browser-based tuning dashboard for servo motor controllers."""

__version__ = "0.1.0"
