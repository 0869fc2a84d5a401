"""A deterministic simulation of PBR with a witness (issue 13): the real pure classes of aft_ftm
(Witness, CheckpointSender, CheckpointReceiver, ProtocolCore, PendingTable, the recovery plans)
wired by models of the ROS adapters' rules, on a discrete-event network with seeded faults.

- :mod:`sim.world`: simulated time, hosts, links, processes, delays, stalls and crashes.
- :mod:`sim.replica`: the nodes of a replica site, the witness and the clients' Proxies, each
  following the rules of its ROS adapter (aft_ftm.ros.*), without rospy.
- :mod:`sim.properties`: the properties users rely on, checked after every step.
- :mod:`sim.schedule`: seeded random schedules of faults, and the runner.
"""
