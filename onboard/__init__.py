"""irtrack onboard service: tracking and single-camera 3-D trajectory reconstruction."""
