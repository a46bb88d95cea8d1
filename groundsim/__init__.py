"""irtrack ground simulator: JSBSim flight, IR rendering, MAVLink + zenoh emitters, evaluation."""
