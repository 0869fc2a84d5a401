"""A rospy node's XML-RPC thread must end when the node shuts down, not spin.

rosgraph's ``XmlRpcNode.shutdown`` closes the server's socket but never ends ``serve_forever``
(ros/ros_comm#2238, never fixed in ROS 1): the loop then polls a closed descriptor, which is ready at
once, for ever, and the thread takes a whole core until the process exits. A node being stopped
(roslaunch's SIGINT, a site relaunched, an adaptation retiring it) spends its last second or more
that way; the crash detector runs every thread under SCHED_FIFO, so its spinning thread took a core
from every ordinary process of the machine: measured beside ``bench_healing``, two detectors
stopping held both cores for up to 950 ms of every second (the real-time throttle's share) for
seconds, the applications of other sites answered nothing meanwhile, and heartbeats elsewhere
came late (false suspicions at 30 ms).

:func:`end_serving_on_shutdown` makes the shutdown ask the loop to end (the flag that
``BaseServer.shutdown`` sets) before the socket is closed, and marks the node shut down first so
that rosgraph's outer loop does not start serving again.
"""
import threading

_FLAG = '_BaseServer__shutdown_request'   # socketserver.BaseServer's private request to end serve_forever


def stop_loop(server):
    """Ask server's serve_forever loop to end at its next turn, without waiting for it."""
    if hasattr(server, _FLAG):
        setattr(server, _FLAG, True)
    else:   # another socketserver: its public shutdown() waits for the loop, so not in this thread
        threading.Thread(target=server.shutdown, daemon=True, name='xmlrpc-shutdown').start()


def end_serving_on_shutdown():
    """Patch rosgraph.xmlrpc.XmlRpcNode.shutdown (once per process, before init_node: rospy keeps the
    bound method it registers then). ``run_node`` calls it."""
    import rosgraph.xmlrpc
    cls = rosgraph.xmlrpc.XmlRpcNode
    original = cls.shutdown
    if getattr(original, 'ends_serving', False):
        return

    def shutdown(self, reason):
        server = self.server
        self.is_shutdown = True   # first: rosgraph's _run serves again while it is False
        if server is not None:
            stop_loop(server)
        return original(self, reason)
    shutdown.ends_serving = True
    cls.shutdown = shutdown
