"""Faithful ports of the report's implementations, kept as baselines for the benchmarks."""
