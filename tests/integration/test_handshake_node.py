"""A node's TCPROS server keeps answering while connections that send no header hold it.

A CI run lost a switch because a replacement After could not reach the witness for 30 s: rospy
reads each inbound header in its one accept thread, with a listen backlog of 5. Here a real witness
gets a connection that stopped in the middle of its header, six that send nothing, and the master's
HTTP call meant for a dead node that had the port before; a service call and a subscription made
after them must still be served at once (before the 10 s a stuck header is allowed), and the
witness logs the refused HTTP call. Runs in a process of its own with a master of its own; every
process it starts carries the test's AFT_TEST_TAG and is killed at the end."""
from leftovers import run_tagged

SCRIPT = r'''
import socket, struct, subprocess, sys, tempfile, time
import rosgraph, rospy
from aft_msgs.msg import Configuration
from aft_msgs.srv import Witness
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until
log_dir = tempfile.mkdtemp(prefix='aft_handshake_')
core = start_master(log_dir)
witness = subprocess.Popen(['rosrun', 'aft_ftm', 'witness', '__name:=witness', '_initial_primary:=master'],
                           stdout=open(log_dir + '/witness.out', 'w'), stderr=subprocess.STDOUT)
held = []
try:
    rospy.init_node('checker')
    rospy.wait_for_service('/witness/request', 30)
    uri = rosgraph.Master('/checker').lookupService('/witness/request')
    host, port = rospy.core.parse_rosrpc_uri(uri)

    def connect():
        s = socket.create_connection((host, port), 5)
        held.append(s)
        return s
    part = b'service=/witness/request'
    connect().sendall(struct.pack('<I', 200) + struct.pack('<I', len(part)) + part[:5])   # stopped mid-header
    for _ in range(6):
        connect()                                                                          # silent
    connect().sendall(b'POST /RPC2 HTTP/1.1\r\nHost: vm\r\nContent-Length: 0\r\n\r\n')  # the master's call
    t0 = time.monotonic()
    call = rospy.ServiceProxy('/witness/request', Witness)
    answer = call(op=0, site='checker')
    service_s = time.monotonic() - t0
    configurations = []
    rospy.Subscriber('/witness/configuration', Configuration, configurations.append)
    if not wait_until(lambda: configurations, 8.0, 0.01):
        sys.exit('no latched configuration within 8 s while the witness held stuck connections')
    subscribe_s = time.monotonic() - t0
    print('served: epoch %d, service after %.2f s, subscription after %.2f s' % (answer.epoch, service_s, subscribe_s))
    if subscribe_s > 8.0:
        sys.exit('served only after the stuck connections were given up (%.1f s)' % subscribe_s)
    out = log_dir + '/witness.out'
    if not wait_until(lambda: 'not a TCPROS handshake' in open(out).read(), 5.0, 0.1):
        sys.exit('the refused HTTP call was not logged: %s' % open(out).read()[-2000:])
    print('refused logged')
finally:
    for s in held:
        s.close()
    witness.terminate()
    witness.wait(10)
    core.stop()
'''


def test_a_witness_held_by_stuck_and_foreign_connections_still_answers_at_once():
    code, output = run_tagged(SCRIPT, timeout=120, home_prefix='aft_handshake_home_')
    assert code == 0, output[-3000:]
    assert 'served: epoch' in output and 'refused logged' in output, output[-3000:]
