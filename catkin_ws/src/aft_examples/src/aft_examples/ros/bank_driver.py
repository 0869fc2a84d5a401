"""The bank client inside an emulated host, driven by an orchestrator outside it.

The orchestrator (a test, the demo, the benchmark) runs in the machine's root namespace and cannot
reach the hosts' network: it starts this driver in the client host (``rosrun aft_examples
bank_driver``) and talks to it over stdin/stdout, one JSON object per line each way. Each command
is answered by one line ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}``; ``drive`` also
prints ``{"event": "fault_point"}`` the moment the reply that triggers a fault came back.

Commands (``op``):
- ``check``: ``services``, ``subscriptions`` ([topic, node] pairs), ``wired`` (a node name, or
  null), ``witness`` (bool): what is missing, whether the node's publishers are all connected, the
  witness's (epoch, primary, backup);
- ``drive``: ``count``, ``first``, ``fault_after`` (null: none): sends operations through
  /account, checks each reply (records [index, sent, replied, ok] and the checker's summary);
- ``call``: one operation ``index`` waited for at most ``timeout`` s (``answered`` false if not);
- ``state``: ``site``: its bank server's state (hex);
- ``failover``: ``site``, ``timeout``: the last failover record of its Recovery;
- ``alarms``: every aft_msgs/Alarm heard on /aft/alarms since the driver started;
- ``strings``: ``topic``, ``last`` (0: all): the std_msgs/String (JSON) heard on it since the first
  ``strings`` of that topic (which subscribes);
- ``quit``.
"""
import json
import sys
import threading
import time

import rospy
from aft_msgs.msg import Alarm
from aft_msgs.srv import Account, GetState
from std_msgs.msg import String

from aft_examples.bank import ReplyChecker, operation
from aft_examples.ros.bank_nodes import account_caller, drive
from aft_examples.ros.deployment import last_failover, witness_status
from aft_ftm.ros.graph import missing_from_graph, wired


class BankDriver(object):
    """Runs the orchestrator's commands (module docstring) in the client host.

    Subscribes:
        /aft/alarms (aft_msgs/Alarm): kept for the ``alarms`` command.
        any std_msgs/String topic a ``strings`` command names.
    Services called:
        /account (aft_msgs/Account), /<site>/bank_server/get_state (aft_msgs/GetState),
        /aft/witness/request (aft_msgs/Witness)
    """

    def __init__(self, out=sys.stdout):
        self.out = out
        self.checker = ReplyChecker()
        self.alarms = []
        self.strings = {}          # topic -> every message heard (``strings``)
        self.lock = threading.Lock()
        self.account = None

    def setup(self, timeout):
        rospy.Subscriber('/aft/alarms', Alarm, self._on_alarm, tcp_nodelay=True)
        return True

    def _on_alarm(self, msg):
        with self.lock:
            self.alarms.append({'mechanism': msg.mechanism, 'kind': msg.kind, 'source': msg.source, 'detail': msg.detail,
                                'stamp': msg.stamp.to_sec()})

    def write(self, data):
        self.out.write(json.dumps(data) + '\n')
        self.out.flush()

    def serve(self, lines):
        """Answer each command line until ``quit`` or the end of input."""
        for line in lines:
            if not line.strip():
                continue
            try:
                command = json.loads(line)
                op = command.get('op')
                if op == 'quit':
                    self.write({'ok': True})
                    return
                handler = getattr(self, 'do_' + str(op), None)
                if handler is None:
                    raise ValueError('unknown command %r' % (op,))
                answer = handler(command)
                self.write(dict(answer, ok=True))
            except Exception as e:   # the orchestrator gets the reason; the driver goes on
                self.write({'ok': False, 'error': '%s: %s' % (type(e).__name__, e)})

    def do_check(self, command):
        took, started = [], time.monotonic()

        def timed(what, function, *args):
            t0 = time.monotonic()
            try:
                return function(*args)
            finally:
                took.append('%s %.2f s' % (what, time.monotonic() - t0))
        status = timed('witness', witness_status) if command.get('witness') else None
        node = command.get('wired')
        answer = {'missing': timed('graph', missing_from_graph, command.get('services', ()),
                                   [tuple(s) for s in command.get('subscriptions', ())]),
                  'wired': bool(timed('wired', wired, node)) if node else True,
                  'witness': [status.epoch, status.primary, status.backup] if status is not None else None}
        if time.monotonic() - started > 2.0:
            # The orchestrator gives a check 10 s: a slow one says which part was slow (bank_driver.log).
            rospy.logwarn('bank_driver: a slow check, %.2f s: %s', time.monotonic() - started, ', '.join(took))
        return answer

    def _proxy(self):
        if self.account is None:
            rospy.wait_for_service('/account', 10.0)
            self.account = rospy.ServiceProxy('/account', Account, persistent=True)
        return self.account

    def do_drive(self, command):
        count, first, fault_after = int(command['count']), int(command.get('first', 0)), command.get('fault_after')
        call = account_caller(self._proxy())

        def on_reply(i):
            if fault_after is not None and i + 1 - first == int(fault_after):
                self.write({'event': 'fault_point', 'index': i, 'wall': time.time()})
        records = drive(call, count, self.checker, on_reply=on_reply, first=first)
        return {'records': records, 'summary': self.checker.summary()}

    def do_call(self, command):
        index, timeout = int(command['index']), float(command.get('timeout', 5.0))
        op, amount = operation(index)
        result = {}

        def call():
            try:
                reply = rospy.ServiceProxy('/account', Account)(op=op, amount=amount)
                result['reply'] = [reply.balance, reply.count, reply.digest]
            except Exception as e:   # reported to the orchestrator
                result['error'] = str(e)
        thread = threading.Thread(target=call, daemon=True)
        sent = time.time()
        thread.start()
        thread.join(timeout)
        return {'answered': 'reply' in result, 'reply': result.get('reply'), 'error': result.get('error'),
                'sent': sent, 'waited': time.time() - sent}

    def do_state(self, command):
        state = rospy.ServiceProxy('/%s/bank_server/get_state' % command['site'], GetState)().state
        return {'state': bytes(state).hex()}

    def do_failover(self, command):
        return {'record': last_failover(command['site'], float(command.get('timeout', 10.0)))}

    def do_alarms(self, command):
        with self.lock:
            return {'alarms': list(self.alarms)}

    def do_strings(self, command):
        topic = rospy.resolve_name(str(command['topic']))
        with self.lock:
            if topic not in self.strings:
                self.strings[topic] = []
                rospy.Subscriber(topic, String, lambda m: self._on_string(topic, m))
            last = int(command.get('last') or 0)
            return {'messages': list(self.strings[topic][-last:] if last else self.strings[topic])}

    def _on_string(self, topic, msg):
        try:
            data = json.loads(msg.data)
        except ValueError:
            data = {'text': msg.data}
        with self.lock:
            self.strings[topic].append(data)
