"""Traffic Jam Pilot case study on a pybullet car (issue 5). So far: the control logic (control),
the sensor fault tolerance (filters) and the FMECA as data (fmeca); the simulation is to come."""
