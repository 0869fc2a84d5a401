"""Traffic Jam Pilot case study on a pybullet car. Skeleton: the simulation arrives with issue 5."""
