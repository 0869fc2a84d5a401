"""ROS adapters of aft_ftm: thin rospy classes around the logic in :mod:`aft_ftm`."""
