"""The per-frame pipeline (:mod:`onboard.pipeline.frame_pipeline`) and the estimator plug-ins.

Imports core, imaging and estimation; no zenoh, pymavlink, sockets or processes: the service drives it
with step methods and the tests drive it without a network."""
