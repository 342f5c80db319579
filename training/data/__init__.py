"""Training data: motion capture loading and dataset building."""
