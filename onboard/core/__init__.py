"""The core: frame conventions, poses, the track and the IR frame types, the error types.

Pure: imports numpy, scipy, pymap3d and the standard library only -- no zenoh, pymavlink, OpenCV,
sockets, threads or processes (tests/test_architecture.py checks it)."""
