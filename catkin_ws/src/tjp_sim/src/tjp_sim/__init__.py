"""Traffic Jam Pilot case study on a pybullet car (issue 5, in progress). So far, without ROS: the
road and its sensors in pybullet (world), the control logic (control), the sensor fault tolerance
(filters) and the FMECA as data (fmeca). The ROS nodes, scenarios and fault injection are to come."""
