"""Per-frame depth and confidence, geometric uncertainty."""
