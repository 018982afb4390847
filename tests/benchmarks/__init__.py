"""Benchmarks: scripts that print figures (run by hand, never collected by pytest); the
accounting modules they share are imported by tests as ``tests.benchmarks.<module>``."""
