"""The devices servotune knows, one folder each; the registry is step (b)."""
