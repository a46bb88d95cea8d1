"""The applications: configuration, the daemon service and its entry point, health, watchdog, replay and
the offline reconstruction.  May import everything in onboard; nothing in onboard imports app."""
