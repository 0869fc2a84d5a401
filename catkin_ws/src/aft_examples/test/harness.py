"""Shared by the rostest scripts of aft_ftm: deployments started and always stopped, the
client-side checks, and the figures the tests report."""
import atexit
import contextlib
import json
import os
import random
import signal
import sys
import tempfile
import time
import unittest

import rospy
from aft_msgs.msg import Alarm
from aft_msgs.srv import Account, GetState

from aft_examples.bank import Account as Model, ReplyChecker, account_state, operation
from aft_examples.ros.bank_nodes import account_caller, drive_through_fault
from aft_examples.ros.deployment import MechanismDeployment, PbrDeployment, last_failover, witness_status
from aft_ftm import suite

LIVE = []
SEED = int(os.environ.get('AFT_TEST_SEED', int(time.time())))
RNG = random.Random(SEED)


# The families of cases the short suite draws from (aft_ftm.suite): a case of one runs only if drawn.
FAMILIES = suite.Families()


def family(name, keep):
    """Declares a test method, or a TestCase class (its every method, not a subclass's), a member of family
    name, of which the short suite runs keep."""
    def declare(thing):
        FAMILIES.add(name, keep, thing.__name__ if isinstance(thing, type) else thing.__qualname__)
        return thing
    return declare


def skip_unless_drawn(case):
    """case.skipTest() if its class or method is of a family and not drawn this time, said on the output
    (rostest's summary counts a skipped case as passed)."""
    method = getattr(type(case), case._testMethodName)
    why = FAMILIES.skip_reason(type(case).__name__) or FAMILIES.skip_reason(method.__qualname__)
    if why:
        suite.say_not_drawn('%s.%s' % (type(case).__name__, case._testMethodName), why)
        case.skipTest(why)


def stop_all(*_):
    while LIVE:
        LIVE.pop().teardown()


class _Stopped(object):
    """A process the test stopped (SIGSTOP): in LIVE while stopped, so that a signal to the test
    (stop_all, last in first out) resumes it before anything that may need it is torn down."""

    def __init__(self, proc):
        self.proc = proc

    def teardown(self):
        try:
            self.proc.resume()
        except Exception:   # psutil.NoSuchProcess: gone meanwhile
            pass


@contextlib.contextmanager
def stopped(proc):
    """proc (a psutil.Process) stopped for the block, resumed after it, pass or fail, or on a signal."""
    entry = _Stopped(proc)
    LIVE.append(entry)
    proc.suspend()
    try:
        yield
    finally:
        entry.teardown()
        if entry in LIVE:
            LIVE.remove(entry)


def on_signal(signum, _frame):
    stop_all()
    os._exit(128 + signum)


def pid_of(node):
    """The pid of a running node (asked through its XML-RPC API, as fencing does)."""
    from aft_ftm.ros.fencing import NamespaceFence
    fence = NamespaceFence(node.rsplit('/', 1)[0], '/aft_test')
    fence.learn()
    return fence.known[node][0]


def sequential_state(count):
    model = Model()
    for i in range(count):
        model.apply(*operation(i))
    return model.snapshot()


def report(name, figures):
    print('RESULT %s %s' % (name, json.dumps(figures, sort_keys=True)))
    sys.stdout.flush()
    out = os.environ.get('AFT_RESULTS_DIR')
    if out:
        os.makedirs(out, exist_ok=True)
        with open(os.path.join(out, '%s.json' % name), 'w') as f:
            json.dump(figures, f, indent=1, sort_keys=True)


class Sites(unittest.TestCase):
    """Starts self.make_deployment() before each test and stops it after, pass or fail."""

    def make_deployment(self, log_dir):
        raise NotImplementedError

    def setUp(self):
        skip_unless_drawn(self)   # before anything starts
        # A site that does not come up is started afresh once: on a loaded 2-core machine rospy has
        # been seen to leave a subscriber's handshake hanging for 60 s, or a node's registration to
        # be interrupted. What the tests check starts once the sites are up, so this hides no
        # behaviour under test; both tries are logged.
        for attempt in (1, 2):
            self.deployment = self.make_deployment(tempfile.mkdtemp(prefix='aft_test_'))
            LIVE.append(self.deployment)
            try:
                self.deployment.start()
                break
            except RuntimeError as e:
                print('deployment start %d failed: %s' % (attempt, e))
                sys.stdout.flush()
                self.tearDown()   # unittest does not call tearDown when setUp fails
                if attempt == 2:
                    raise
        self.account = rospy.ServiceProxy('/account', Account)
        self.account.wait_for_service(30)
        self.checker = ReplyChecker()
        self.call = account_caller(self.account)

    def tearDown(self):
        self.deployment.teardown()
        if self.deployment in LIVE:
            LIVE.remove(self.deployment)

    def assert_pair_intact(self):
        """The witness's configuration is still MASTER primary, SLAVE backup: no false suspicion before the
        test's fault (whose figures would then measure something else). Deployments without a witness
        pass."""
        if not getattr(self.deployment, 'witness', False):
            return
        status = witness_status(self.deployment.witness_service)
        self.assertIsNotNone(status, 'the witness did not answer before the fault')
        self.assertEqual((status.primary, status.backup), ('master', 'slave'),
                         'the pair changed before the fault (a false suspicion?), epoch %d' % status.epoch)

    # True in the classes whose every run_with_crash case handles a preempted fault (processes 0): a pair
    # changed before the fault is then no failure (at 30 ms under load, it happens); otherwise it fails at once.
    PREEMPTIBLE = False

    def pair_changed(self):
        """True if the witness no longer names MASTER primary and SLAVE backup: a false suspicion (the cases at
        30 ms, under load) came between the test's start and its fault, which would then hit a fenced or
        deposed site. False without a witness."""
        if not getattr(self.deployment, 'witness', False):
            return False
        status = witness_status(self.deployment.witness_service)
        return status is None or (status.primary, status.backup) != ('master', 'slave')

    def assert_preempted_exactly_once(self, count, what):
        """The fault was preempted by a false suspicion (pair_changed() at its moment, so not injected): every
        request still answered exactly once, by the site the witness names primary now; said in the output."""
        status = witness_status(self.deployment.witness_service)
        self.assertIsNotNone(status, 'the witness did not answer after a preempted fault')
        self.assert_exactly_once(count, status.primary)
        print('RESULT %s preempted: a false suspicion changed the pair before the fault (now %s/%s, epoch %d); '
              'exactly once held, the fault\'s own path was not run (AFT_SEED=%d)' % (
                  what, status.primary, status.backup, status.epoch, SEED))

    def run_with_crash(self, site, count, crash_after, fault=None):
        """Drive count requests; once crash_after replies came back, power off the site (or run fault()). Not
        injected if pair_changed() then (the returned fault's processes are 0: see
        assert_preempted_exactly_once): with the backup fenced by a false suspicion, powering off the primary
        would leave nobody to serve and the calls would wait for ever."""
        if not self.PREEMPTIBLE:
            self.assert_pair_intact()
        inject = fault or self.deployment.sites[site].power_off_fault

        def unless_preempted():
            return (0, time.time()) if self.pair_changed() else inject()
        return drive_through_fault(self.call, count, self.checker, crash_after, unless_preempted, RNG)

    def state_of(self, site):
        get = rospy.ServiceProxy('/%s/bank_server/get_state' % site, GetState)
        model = Model()
        model.set_state(account_state(get().state))   # without the ballast, if any
        return model.snapshot()

    def assert_exactly_once(self, count, survivor):
        summary = self.checker.summary()
        self.assertEqual(summary, {'correct': count, 'lost': 0, 'duplicated': 0, 'reordered': 0, 'errors': 0},
                         'some replies were wrong: %s' % summary)
        self.assertEqual(self.state_of(survivor), sequential_state(count),
                         'the surviving server state differs from a failure-free sequential run')

    def recovery_event(self, site):
        """The site's last failover record (Recovery's ~events, latched: other records carry it)."""
        return last_failover(site)


class PbrSites(Sites):
    MECHANISM = 'pbr'
    ONE_HOST = False
    INNER = ''
    FAULTY = False
    SEC = False
    ADAPTABLE = False
    # The crash detectors' timeout (s), heartbeats every 10 ms. 300 ms unless the test measures
    # detection or failover time (those set 0.03, the default of the launch files): on a loaded 2-core
    # CI machine a 30 ms detector has suspected a healthy peer and fenced it before the test's own
    # fault, and the test then failed on something it does not check (issue 15 measures that rate).
    DETECTION_TIMEOUT = 0.3
    SERVER_TIMEOUT = None      # Proceed's server timeout (s); None: the launch files' default
    CACHE_BYTES = None         # bound of the replicas' reply caches (bytes); None: the launch files' default
    BALLAST_BYTES = 0          # inert bytes added to the bank server's state (0: its ~60 bytes, sent whole)
    CA_VALIDITY = None         # SEC: a certificate's life (s); None: the CA's default (24 h)
    CHUNK_BYTES = None         # PBR: a join's state transfer in parts of this many bytes; None: the default (1 MiB)

    def make_deployment(self, log_dir):
        return PbrDeployment(log_dir, one_host=self.ONE_HOST, inner=self.INNER, faulty=self.FAULTY,
                             mechanism=self.MECHANISM, sec=self.SEC, adaptable=self.ADAPTABLE,
                             timeout=self.DETECTION_TIMEOUT, server_timeout=self.SERVER_TIMEOUT,
                             cache_bytes=self.CACHE_BYTES, ballast_bytes=self.BALLAST_BYTES,
                             ca_validity=self.CA_VALIDITY, chunk_bytes=self.CHUNK_BYTES)


class MechanismSite(Sites):
    MECHANISM = None
    INNER = ''
    EXECUTIONS = 3

    def make_deployment(self, log_dir):
        return MechanismDeployment(log_dir, self.MECHANISM, executions=self.EXECUTIONS, inner=self.INNER)


class AlarmLog(object):
    """Collects the aft_msgs/Alarm of a topic."""

    def __init__(self, topic='/aft/alarms'):
        self.alarms = []
        self.sub = rospy.Subscriber(topic, Alarm, self.alarms.append, tcp_nodelay=True)

    def kinds(self, kind):
        return [a for a in self.alarms if a.kind == kind]

    def wait_connected(self, publishers, timeout=10.0):
        """Wait until at least publishers alarm publishers are connected to this log."""
        from aft_ftm.sites import wait_until
        return wait_until(lambda: self.sub.get_num_connections() >= publishers, timeout)

    def wait_for(self, kind, timeout=10.0):
        from aft_ftm.sites import wait_until
        return wait_until(lambda: self.kinds(kind), timeout)

    def close(self):
        self.sub.unregister()


def run(package, name):
    """The test script's main: a node without rospy's signal handlers, and every TestCase of it."""
    rospy.init_node(name, disable_signals=True)
    atexit.register(stop_all)
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    print('AFT_TEST_SEED=%d' % SEED)
    print('AFT_SUITE=%s AFT_SUITE_SEED=%d' % (suite.suite(), suite.seed()))
    import rostest
    only = os.environ.get('AFT_TEST_ONLY', '')
    if only:
        # A development aid: only the test methods whose name holds AFT_TEST_ONLY (said, never silent;
        # rostest builds its own loader, so the pattern is set on the class).
        unittest.TestLoader.testNamePatterns = ['*%s*' % only]
        count = unittest.TestLoader().loadTestsFromName('__main__').countTestCases()
        print('AFT_TEST_ONLY=%s: only the %d test method(s) whose name holds it' % (only, count))
        if not count:
            sys.exit('AFT_TEST_ONLY=%s: no test method of %s holds it' % (only, name))
    rostest.rosrun(package, name, '__main__')
