"""Metrics, timing and benchmarks."""
