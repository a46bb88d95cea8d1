"""Adapters: MAVLink (autopilot link, ground-station link, the camera protocol, tracking and follow
messages), zenoh, H.264 video, MCAP recording and the Foxglove live view.

May import core and pipeline types; the only place that imports pymavlink, zenoh, PyAV, mcap or foxglove."""
