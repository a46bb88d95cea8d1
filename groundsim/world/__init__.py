"""The simulated world: scenarios, target motion, JSBSim flight, navigation errors, the IR renderer, the
truth file.  Imports onboard.core only (frame conventions); no sockets, no processes."""
