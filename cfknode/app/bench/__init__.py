"""Benchmarks and the paper reproduction, on the public API."""
