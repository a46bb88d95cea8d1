"""Evaluation: lockstep eval, estimator harness, scoring, reports, demo, campaigns, datasets, baselines."""
