"""Performance benchmarks (``servotune bench``): figures, not tests."""
