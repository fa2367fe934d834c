"""Benchmarks: figures printed as numbers, never asserted (shared machines are noisy)."""
