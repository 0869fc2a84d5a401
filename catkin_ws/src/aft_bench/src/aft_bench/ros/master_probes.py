"""The probes of scripts/bench_master (the ROS master as a single point of failure): bounded calls
over persistent connections, a topic pair with a child node, new lookups, subscriptions and nodes,
and the FTM's failover while the master is dead. The script drives them and prints the report."""
import json
import os
import sys
import threading
import time
from collections import namedtuple

import psutil
import rosgraph
import rospy
from aft_msgs.srv import Account
from std_msgs.msg import String

from aft_examples.bank import Account as Model
from aft_examples.ros.bank_nodes import account_caller
from aft_examples.stats import longest_wait, median
from aft_ftm.sites import Site, process_tree, wait_until


CHATTER, ECHO = '/bench_master/chatter', '/bench_master/echo'
TICKS = '/bench_master/ticks'              # old topic: new subscription while the master is dead
TICKS_LATE = '/bench_master/ticks_late'    # old topic: new subscription after the restart
PROBE = '/bench_master/probe'              # advertised by the node started while the master is dead
FRESH = '/bench_master/fresh'              # new topic of the new nodes after the restart
PEER, PEER_SERVICE = '/bench_master_peer', '/bench_master/peer/account'
RECOVERY_EVENTS = '/slave/recovery/events'

# A child node. role peer: echoes CHATTER on ECHO, offers PEER_SERVICE, publishes TICKS and
# TICKS_LATE; role probe: publishes PROBE; role talker: publishes FRESH. It prints each stage.
CHILD = r'''
import sys
import rospy
from std_msgs.msg import String
from aft_msgs.srv import Account, AccountResponse
role, name = sys.argv[1], sys.argv[2]
print('stage: init_node', flush=True)
rospy.init_node(name)
print('stage: init_node returned', flush=True)
if role == 'peer':
    echo = rospy.Publisher('%(echo)s', String, queue_size=1000, tcp_nodelay=True)
    rospy.Subscriber('%(chatter)s', String, echo.publish, queue_size=1000, tcp_nodelay=True)
    calls = [0]
    def on_call(req):
        calls[0] += 1
        return AccountResponse(balance=calls[0], count=calls[0], digest='peer')
    rospy.Service('%(service)s', Account, on_call)
    topics = ['%(ticks)s', '%(ticks_late)s']
else:
    topics = ['%(probe)s'] if role == 'probe' else ['%(fresh)s']
publishers = [rospy.Publisher(t, String, queue_size=10, tcp_nodelay=True) for t in topics]
print('stage: advertised', flush=True)
rate = rospy.Rate(50)
try:
    while not rospy.is_shutdown():
        for p in publishers:
            p.publish(String(data='tick'))
        rate.sleep()
except rospy.ROSInterruptException:
    pass
''' % {'echo': ECHO, 'chatter': CHATTER, 'service': PEER_SERVICE, 'ticks': TICKS, 'ticks_late': TICKS_LATE,
       'probe': PROBE, 'fresh': FRESH}

# One call: wall-clock times (replied None if no reply came); outcome is one of OUTCOMES.
Record = namedtuple('Record', 'sent replied outcome error')
OUTCOMES = ('correct', 'wrong', 'error', 'no answer', 'not sent')
ANSWERED = ('correct', 'wrong')   # a reply came back (an error reply or a failed call is no answer)


class NoAnswer(rospy.ROSException):
    """A call got no reply within the time limit (it still holds its connection)."""


class ConnectionBusy(rospy.ROSException):
    """A call could not be sent: an earlier unanswered call still holds the connection."""


class BoundedCalls(object):
    """Calls through one connection, one at a time, none waiting more than limit seconds."""

    def __init__(self, call, limit):
        self.call = call
        self.limit = limit
        self.pending = None   # the thread of a call given up, still waiting for its reply

    def __call__(self, *args, **kwargs):
        if self.pending is not None:
            self.pending.join(self.limit)
            if self.pending.is_alive():
                raise ConnectionBusy('not sent: the connection is still held by a call unanswered for more than %.0f s'
                                     % (2 * self.limit))
            self.pending = None
        box = {}

        def run():
            try:
                box['reply'] = self.call(*args, **kwargs)
            except Exception as e:   # handed to the caller below
                box['error'] = e
        thread = threading.Thread(target=run, name='bounded-call', daemon=True)
        thread.start()
        thread.join(self.limit)
        if thread.is_alive():
            self.pending = thread
            raise NoAnswer('no reply within %.1f s' % self.limit)
        if 'error' in box:
            raise box['error']
        return box['reply']


class AccountClient(object):
    """Deposits of 1 through one bounded connection to an aft_msgs/Account service. With a checker
    every reply is checked against the client's model of the account (ReplyChecker); a call
    without a reply leaves the model as it was."""

    def __init__(self, proxy, limit, checker=None):
        self.calls = BoundedCalls(account_caller(proxy), limit)
        self.checker = checker

    def one(self):
        saved = self.checker.model.snapshot() if self.checker else None
        expected = self.checker.expect('deposit', 1) if self.checker else None
        sent = time.time()
        try:
            got = self.calls('deposit', 1)
        except (rospy.ServiceException, rospy.ROSException) as e:
            if self.checker:
                self.checker.model = Model(*saved)
            outcome = 'not sent' if isinstance(e, ConnectionBusy) else 'no answer' if isinstance(e, NoAnswer) else 'error'
            return Record(sent, None, outcome, str(e) or type(e).__name__)
        replied = time.time()
        ok = self.checker.check(expected, got) if self.checker else True
        return Record(sent, replied, 'correct' if ok else 'wrong', '' if ok else 'wrong reply %r' % (got,))

    def series(self, count, until=None):
        """Up to count calls (and until the monotonic time until); stops once a call is left
        unanswered, since it holds the connection."""
        records = []
        while len(records) < count and (until is None or time.monotonic() < until):
            records.append(self.one())
            if records[-1].outcome in ('no answer', 'not sent'):
                break
        return records


def call_summary(records):
    sent = [r for r in records if r.outcome != 'not sent']
    answered = [r for r in sent if r.outcome in ANSWERED]
    errors = [r.error for r in records if r.error]
    return {'sent': len(sent), 'answered': len(answered), 'correct': sum(1 for r in sent if r.outcome == 'correct'),
            'lost': len(sent) - len(answered), 'median_s': median([r.replied - r.sent for r in answered]),
            'outcomes': {o: sum(1 for r in records if r.outcome == o) for o in OUTCOMES if any(r.outcome == o for r in records)},
            'error': errors[0] if errors else ''}


def one_lookup(checker, limit):
    """A non-persistent call to /account: rospy asks the master for the service's address first."""
    client = AccountClient(rospy.ServiceProxy('/account', Account, persistent=False), limit, checker)
    t0 = time.monotonic()
    record = client.one()
    return {'ok': record.outcome == 'correct', 'seconds': time.monotonic() - t0, 'error': record.error,
            'outcome': record.outcome}


class Echoes(object):
    """The established topic pair: this process publishes on CHATTER, the peer echoes on ECHO."""

    def __init__(self):
        self.received = []
        self.sub = rospy.Subscriber(ECHO, String, lambda m: self.received.append(m.data), queue_size=1000,
                                    tcp_nodelay=True)
        self.pub = rospy.Publisher(CHATTER, String, queue_size=1000, tcp_nodelay=True)

    def connected(self):
        return self.pub.get_num_connections() >= 1 and self.sub.get_num_connections() >= 1

    def burst(self, tag, count, seconds):
        """count messages over seconds; the echoes that came back (0.5 s more allowed)."""
        for k in range(count):
            self.pub.publish(String(data='%s:%d' % (tag, k)))
            time.sleep(seconds / count)

        def heard():
            return sum(1 for d in list(self.received) if d.startswith(tag + ':'))
        wait_until(lambda: heard() >= count, 0.5, 0.01)
        got = heard()
        return {'sent': count, 'received': got, 'lost': count - got}


def publishers_of(topic):
    try:
        pubs, _, _ = rosgraph.Master('/bench_master_probe').getSystemState()
    except Exception as e:   # no master: say so
        return 'unknown (%s)' % e
    return sorted(n for t, nodes in pubs if t == topic for n in nodes)


# Threads creating a rospy.Subscriber: while one is blocked (no master), it holds rospy's topic
# manager lock, and rospy.signal_shutdown() (also run at exit) deadlocks on that lock, because the
# registration loop only stops once the shutdown flag is set, after the pre-shutdown hooks.
REGISTRATIONS = []


def registration_pending():
    return any(t.is_alive() for t in REGISTRATIONS)


def new_subscription(topic, wait):
    """A new subscriber in this process to topic: what it receives within wait seconds."""
    got = []
    t0 = time.monotonic()
    thread = threading.Thread(target=lambda: rospy.Subscriber(topic, String, lambda m: got.append(time.monotonic()),
                                                              queue_size=100, tcp_nodelay=True),
                              name='new-subscription', daemon=True)
    REGISTRATIONS.append(thread)
    thread.start()
    thread.join(wait)
    wait_until(lambda: got, max(0.0, wait - (time.monotonic() - t0)), 0.01)
    result = {'ok': bool(got), 'received': len(got), 'subscriber_returned': not thread.is_alive(),
              'first_message_s': (got[0] - t0) if got else None, 'error': ''}
    if thread.is_alive():
        result['error'] = ('rospy.Subscriber() still blocked after %.1f s: rospy retries registerSubscriber every '
                           '0.2 s until a master answers (and holds its registration lock meanwhile)' % wait)
    elif not got:
        result['error'] = ('registered, but nothing received within %.1f s; publishers of %s the master knows: %s'
                           % (wait, topic, publishers_of(topic)))
    return result


def child(log_dir, role, name):
    return Site(name, [sys.executable, '-c', CHILD, role, name], log_path=os.path.join(log_dir, name + '.log'))


def last_stage(site):
    try:
        with open(site.log_path) as f:
            stages = [line.strip() for line in f if line.startswith('stage: ')]
    except OSError:
        return ''
    return stages[-1][len('stage: '):] if stages else ''


def new_node(log_dir, name, wait):
    """A child node started now: is it up (init_node returned and a topic advertised) within wait s?"""
    site = child(log_dir, 'probe', name).start()
    try:
        t0 = time.monotonic()
        up = wait_until(lambda: last_stage(site) == 'advertised', wait, 0.02)
        seconds = time.monotonic() - t0
        error = '' if up else 'not up within %.1f s: stuck at %s (log %s)' % (wait, last_stage(site) or 'start',
                                                                             site.log_path)
        return {'ok': bool(up), 'seconds': seconds, 'error': error, 'stage': last_stage(site)}
    finally:
        site.stop(grace=2.0)


def new_nodes(log_dir, name, wait):
    """After the restart: a new subscriber here on a new topic, then a new child publishing on it
(50 Hz): is anything received within wait seconds, and how much over the second after the first."""
    got = []
    t0 = time.monotonic()
    sub = rospy.Subscriber(FRESH, String, lambda m: got.append(time.monotonic()), queue_size=100, tcp_nodelay=True)
    site = child(log_dir, 'talker', name).start()
    try:
        if wait_until(lambda: got, wait, 0.01):
            time.sleep(1.0)   # the child publishes at 50 Hz: count for 1 s more
        return {'ok': bool(got), 'received': len(got), 'first_message_s': (got[0] - t0) if got else None,
                'error': '' if got else 'nothing received within %.1f s; child at %s' % (wait, last_stage(site))}
    finally:
        site.stop(grace=2.0)
        sub.unregister()


def registrations():
    """node -> its registrations, from the master."""
    pubs, subs, srvs = rosgraph.Master('/bench_master_probe').getSystemState()
    nodes = {}
    for kind, table in (('pub', pubs), ('sub', subs), ('srv', srvs)):
        for name, names in table:
            for node in names:
                nodes.setdefault(node, []).append('%s %s' % (kind, name))
    return nodes


def find_rosmaster(core):
    for proc in process_tree(core.pid):
        try:
            if any(os.path.basename(a) == 'rosmaster' for a in proc.cmdline()[:2]):
                return proc
        except psutil.Error:
            pass
    return None


def ftm_failover(client, site, before, after, limit, rng, events):
    """Calls over the client's persistent connection; after `before` of them the PBR MASTER site is
    powered off (at a random instant inside a call) and up to `after` more calls are made, for at
    most 2 x limit seconds."""
    records = client.series(before)
    crash, attempted = {}, []

    def inject():
        time.sleep(rng.uniform(0, 0.003))
        attempted.append(time.time())
        crash['processes'], crash['wall'] = site.power_off_fault()
    mark = len(events)
    thread = threading.Thread(target=inject, name='power-off', daemon=True)
    thread.start()
    records += client.series(after, until=time.monotonic() + 2 * limit)
    thread.join(10)
    stopped_before = None
    if crash.get('wall') is None:
        if 'processes' not in crash:
            return {'sent': 0, 'answered': 0, 'correct': 0, 'lost': 0, 'longest_wait_s': None,
                    'backup_serving': False, 'error': 'the MASTER site could not be powered off'}
        # power_off() found nothing to kill: the site had already stopped (its nodes fail-stopped, e.g.
        # deposed after a false suspicion). A finding to report; the calls split at the attempt.
        stopped_before = ('the MASTER site had already stopped (exit code %s) before the power-off; see %s'
                          % (site.proc.returncode if site.proc else None, site.log_path))
        crash['wall'] = attempted[0]
    wait_until(lambda: len(events) > mark, 1.0, 0.01)   # the backup's recovery report, if one comes
    summary = call_summary(records)
    answered = [(i, r.sent, r.replied, r.outcome == 'correct') for i, r in enumerate(records) if r.outcome in ANSWERED]
    after_crash = [r for r in records if r.sent > crash['wall']]
    unanswered = [r for r in records if r.outcome in ('no answer', 'error')]
    recovery = json.loads(events[mark]) if len(events) > mark else None
    result = {'sent': summary['sent'], 'answered': summary['answered'], 'correct': summary['correct'],
              'lost': summary['lost'], 'longest_wait_s': longest_wait(answered, crash['wall']),
              'backup_serving': any(r.outcome == 'correct' for r in after_crash),
              'error': stopped_before or summary['error'],
              'calls_after_crash': len([r for r in after_crash if r.outcome != 'not sent']),
              'processes_killed': crash['processes'],
              'first_unanswered_waited_s': (limit if unanswered and unanswered[0].outcome == 'no answer' else None),
              'recovery': None if recovery is None else {
                  'ok': recovery.get('ok'), 'seconds': recovery.get('seconds'),
                  'steps': [{'step': s['step'], 'ok': s['ok'], 'detail': s['detail']} for s in recovery['steps']]}}
    return result
