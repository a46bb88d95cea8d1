"""Baseline algorithms written only against :mod:`onboard.plugins` (as an outside package would be)."""
