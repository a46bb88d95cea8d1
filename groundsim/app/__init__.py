"""The simulator's command line (python -m groundsim) and its real-time run loop."""
