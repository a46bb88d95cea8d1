"""Baseline algorithms written only against :mod:`onboard.pipeline.plugins` (as an outside package would be)."""
