"""Benchmarks: print numbers, never assert on time."""
