"""Benchmarks: each writes JSON with median timings and the machine."""
