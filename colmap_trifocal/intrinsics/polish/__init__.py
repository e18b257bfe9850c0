"""polish."""
