"""The simulator's adapters: the simulated MAVLink vehicle and camera stream over zenoh, the video receiver."""
