"""Accuracy statistics, the drift watch, diagnosis and adaptation runs (API and job side), and
their routes."""
