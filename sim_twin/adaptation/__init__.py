"""Adaptation of a policy version to a diagnosed site (`slinger adapt`), with its aim anchor."""
