"""A stopped node's XML-RPC thread ends instead of spinning (aft_ftm.ros.xmlrpc_shutdown). No ROS master:
rosgraph's XML-RPC server alone, in a process of its own, its CPU time measured after its shutdown."""
import subprocess
import sys

import pytest

pytest.importorskip('rosgraph')

PROGRAM = r'''
import sys, time
import rosgraph.xmlrpc
if sys.argv[1] == 'patched':
    from aft_ftm.ros.xmlrpc_shutdown import end_serving_on_shutdown
    end_serving_on_shutdown()
node = rosgraph.xmlrpc.XmlRpcNode(0, rosgraph.xmlrpc.XmlRpcHandler())
node.start()
deadline = time.monotonic() + 10
while node.uri is None and time.monotonic() < deadline:
    time.sleep(0.01)
assert node.uri, 'the XML-RPC server did not start'
time.sleep(0.2)
node.shutdown('test')
cpu = time.process_time()
time.sleep(1.0)
print(time.process_time() - cpu)
'''


def cpu_after_shutdown(mode):
    out = subprocess.run([sys.executable, '-c', PROGRAM, mode], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return float(out.stdout.split()[-1])


def test_a_shut_down_xmlrpc_server_takes_no_cpu_once_patched_and_a_core_without():
    # Without the patch, rosgraph's loop polls the closed socket for ever (ros/ros_comm#2238):
    # about a core for the second measured. If this ever fails, rosgraph fixed it itself.
    assert cpu_after_shutdown('plain') > 0.3
    assert cpu_after_shutdown('patched') < 0.05
