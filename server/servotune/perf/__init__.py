"""Performance benchmarks (``servotune perf``): figures, not tests."""
