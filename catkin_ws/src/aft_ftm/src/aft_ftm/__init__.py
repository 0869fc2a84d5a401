"""AFT-ROS: Adaptive Fault Tolerance for ROS 1.

The modules directly in this package hold the logic of the fault tolerance mechanisms
(duplicate detection, checkpointing, failure detection, replica roles, dynamic binding
rules). They never import rospy and take the current time as an argument, so they are
tested without a ROS master. The ROS adapters live in :mod:`aft_ftm.ros`.
"""
