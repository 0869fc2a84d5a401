"""The demo application: an unmodified bank server and client (no FTM code in them but the
server's state-manager mixin)."""
import json
import sys
import threading
import time
import uuid

import rospy
from aft_msgs.srv import Account, AccountResponse, InjectFault, InjectFaultResponse

from aft_ftm import config
from aft_examples.stats import median
from aft_examples.bank import Account as AccountLogic, InsufficientFunds, ReplyChecker, StateLayout, operation
from aft_ftm.delta import ServerChanges
from aft_ftm.ros.params import param
from aft_ftm.ros.state_manager import StateManager


class BankServerNode(StateManager):
    """A bank account served as a ROS service.

    Parameters:
        ~ballast_bytes (int, 0): bytes of inert state carried before the account (benchmarks of large
            states: scripts/bench_healing); a state whose ballast is not that long is refused.
        ~state_changes (bool, true): offer ~get_state_delta, the changes since a version (aft_examples.bank
            .StateLayout): the account alone; false: getState only (the framework computes the deltas).
    Services:
        account (aft_msgs/Account), ~get_state (aft_msgs/GetState), ~set_state (aft_msgs/SetState),
        ~get_state_delta (aft_msgs/GetStateDelta) unless ~state_changes is false
        ~corrupt_state_changes (aft_msgs/InjectFault, ``count``): the next count answers of get_state_delta
            that carry changes have one byte of them wrong (a faulty server; fault injection for the tests)
        ~fail_state_changes (aft_msgs/InjectFault, ``count``): the next count get_state_delta calls fail, get_state
            still answers (fault injection for the tests)
        ~fail_state_captures (aft_msgs/InjectFault, ``count``): the next count get_state (or get_state_delta)
            calls fail (fault injection for the tests: a state capture failing once, or for good)
        ~slow_state_restores (aft_msgs/InjectFault, ``count``, ``magnitude`` s): the next count set_state
            calls take magnitude seconds before they apply, the account serving meanwhile (a server
            decoding a large state before it swaps it in; fault injection for the tests)
    """

    def __init__(self):
        self.account = AccountLogic()
        self.state_lock = threading.RLock()
        self.capture_faults = 0
        self.slow_restores = (0, 0.0)   # (how many more set_state calls are slow, seconds each)
        self.layout = StateLayout(param('ballast_bytes', config.non_negative_int, 0), uuid.uuid4().hex[:8])
        self.offers_changes = param('state_changes', config.flag, True)
        self.corrupt_changes = 0
        self.changes_faults = 0

    def setup(self, timeout):
        if not self.offers_changes:
            self.state_changes = None   # hides the method: the mixin then offers getState alone
        self.advertise_state_services()
        rospy.Service('account', Account, self._on_request)
        rospy.Service('~corrupt_state_changes', InjectFault, self._on_corrupt_changes)
        rospy.Service('~fail_state_changes', InjectFault, self._on_fail_changes)
        rospy.Service('~fail_state_captures', InjectFault, self._on_fail_captures)
        rospy.Service('~slow_state_restores', InjectFault, self._on_slow_restores)
        return True

    def _on_slow_restores(self, req):
        if req.count and not 0 < req.magnitude <= 60:
            return InjectFaultResponse(success=False, message='magnitude: the delay in s, in (0, 60], got %r'
                                       % req.magnitude)
        with self.state_lock:
            self.slow_restores = (req.count, req.magnitude)
        return InjectFaultResponse(success=True, message='the next %d state restores take %.3f s'
                                   % (req.count, req.magnitude))

    def _handle_set_state(self, req):
        with self.state_lock:
            count, delay = self.slow_restores
            if count:
                self.slow_restores = (count - 1, delay)
        if count:
            time.sleep(delay)   # outside the lock: the account goes on serving meanwhile
        return super(BankServerNode, self)._handle_set_state(req)

    def _on_fail_captures(self, req):
        with self.state_lock:
            self.capture_faults = req.count
        return InjectFaultResponse(success=True, message='the next %d state captures fail' % req.count)

    def _on_corrupt_changes(self, req):
        with self.state_lock:
            self.corrupt_changes = req.count
        return InjectFaultResponse(success=True, message='the next %d state changes told are wrong' % req.count)

    def _on_fail_changes(self, req):
        with self.state_lock:
            self.changes_faults = req.count
        return InjectFaultResponse(success=True, message='the next %d state changes fail' % req.count)

    def _on_request(self, req):
        with self.state_lock:
            try:
                balance, count, digest = self.account.apply(req.op, req.amount, req.tag)
            except (ValueError, InsufficientFunds) as e:
                raise rospy.ServiceException(str(e))
            self.layout.changed()
        return AccountResponse(balance=balance, count=count, digest=digest)

    def _captured(self):
        if self.capture_faults > 0:
            self.capture_faults -= 1
            raise rospy.ServiceException('injected fault: the state cannot be captured')

    def get_state(self):
        self._captured()
        return self.layout.state(self.account.get_state())

    def state_changes(self, since):
        self._captured()
        if self.changes_faults > 0:
            self.changes_faults -= 1
            raise rospy.ServiceException('injected fault: the state changes cannot be told')
        changes = self.layout.since(since, self.account.get_state())
        if changes.runs and self.corrupt_changes > 0:
            self.corrupt_changes -= 1
            start, end, data = changes.runs[0]
            wrong = bytes([data[0] ^ 0x01]) + data[1:]   # the CRC still that of the true state
            changes = ServerChanges(changes.version, runs=[(start, end, wrong)] + changes.runs[1:],
                                    size=changes.size, crc=changes.crc)
        return changes

    def set_state(self, data):
        self.account.set_state(self.layout.account(data))
        self.layout.changed()


def call_failed(index, error):
    """Say that call ``index`` failed: its kind on /rosout, its text only on this process's stderr.
    /rosout is in clear (its node is ROS's own, without TLS), and the text of a failed call may carry
    what SEC sealed on the wire (a server's error about the account), so it stays local (review of
    session 41)."""
    rospy.logerr('request %d failed (%s; its text on the client\'s stderr)', index, type(error).__name__)
    sys.stderr.write('request %d failed: %s\n' % (index, error))


def drive(call, count, checker, on_reply=None, pause=0.0, first=0):
    """Send operations first .. first+count-1 through call(op, amount) -> (balance, count, digest),
    checking each.

    Returns a list of (index, sent_wall, replied_wall, ok) records; failed calls count as errors.
    """
    records = []
    for i in range(first, first + count):
        op, amount = operation(i)
        expected = checker.expect(op, amount)
        sent = time.time()
        try:
            got = call(op, amount)
        except (rospy.ServiceException, rospy.ROSException) as e:
            checker.errors += 1
            call_failed(i, e)
            records.append((i, sent, time.time(), False))
            continue
        ok = checker.check(expected, got)
        records.append((i, sent, time.time(), ok))
        if on_reply:
            on_reply(i)
        if pause:
            time.sleep(pause)
    return records


def drive_with_faults(call, count, checker, faults, limit):
    """drive() count operations in a thread of its own while another runs each fault of ``faults``, a
    list of (replies, fault()) in order, once that many replies came back. Returns (the records, or
    None if the calls did not all end within limit seconds; {replies: what that fault() returned})."""
    at = {after: threading.Event() for after, _ in faults}
    done, out = {}, {}

    def inject():
        for after, fault in faults:
            if not at[after].wait(limit):
                return
            out[after] = fault()

    def client():
        done['records'] = drive(call, count, checker, on_reply=lambda i: at[i + 1].set() if i + 1 in at else None)
    threading.Thread(target=inject, daemon=True).start()
    worker = threading.Thread(target=client, daemon=True)
    worker.start()
    worker.join(limit)
    return done.get('records'), out


def account_proxy(timeout):
    """A proxy of the ``account`` service once it is offered (within timeout), else None (logged)."""
    try:
        rospy.wait_for_service('account', timeout)
    except rospy.ROSException:
        rospy.logerr('%s: service %s not available', rospy.get_name(), rospy.resolve_name('account'))
        return None
    return rospy.ServiceProxy('account', Account)


def account_caller(proxy):
    """Adapt an aft_msgs/Account service proxy to drive()'s call(op, amount) -> (balance, count, digest)."""
    def call(op, amount):
        r = proxy(op=op, amount=amount)
        return r.balance, r.count, r.digest
    return call


def drive_through_fault(call, count, checker, fault_after, fault, rng, max_delay=0.003, first=0, tail=10):
    """drive() count operations; once fault_after replies came back, after a random delay of up to
    max_delay (so that the fault lands anywhere inside the next request), run fault() in another
    thread. fault() returns (processes affected, wall-clock time of the fault).

    The last ``tail`` operations (as many as there are after fault_after) are sent only once fault()
    returned (waiting up to 60 s), so that some are always sent after the fault, however slow fault()
    is (a loaded machine can take longer to stop a site than the client takes for every remaining
    request): the outage is then measured.

    Returns (records, fault) where fault is {'processes', 'wall'}; raises what fault() raised, once
    every call was made, or RuntimeError if the fault was never injected.
    """
    if not 0 < fault_after <= count:
        raise ValueError('fault_after=%d: expected 1 .. count (%d)' % (fault_after, count))
    tail = min(tail, count - fault_after)
    injected = {}
    reached, finished = threading.Event(), threading.Event()

    def inject():
        try:
            if reached.wait(300):
                time.sleep(rng.uniform(0, max_delay))
                injected['processes'], injected['wall'] = fault()
        except Exception as e:   # said in the RuntimeError below
            injected['error'] = e
        finally:
            finished.set()

    def on_reply(i):   # (not called for a failed call: the next reply counts)
        done = i + 1 - first
        if done >= fault_after:
            reached.set()
        if tail and done >= count - tail and not finished.is_set():
            finished.wait(60)

    thread = threading.Thread(target=inject, name='fault', daemon=True)
    thread.start()
    records = drive(call, count, checker, first=first, on_reply=on_reply)
    reached.set()
    thread.join(10)
    if 'error' in injected:
        raise injected['error']
    if 'wall' not in injected:
        raise RuntimeError('the fault was never injected (fault_after=%d, count=%d)' % (fault_after, count))
    return records, injected


class BankClientNode(object):
    """Sends ~count operations to the account service, checks every reply, writes a report.

    Parameters:
        ~count (int, 500), ~pause (float, 0 s between requests), ~report (str: JSON output path, optional)
    Services called:
        account (aft_msgs/Account)
    """

    def __init__(self):
        self.count = param('count', config.non_negative_int, 500)
        self.pause = param('pause', config.non_negative_float, 0.0)
        self.report = param('report', config.non_empty_str, '')

    def setup(self, timeout):
        self.proxy = account_proxy(timeout)
        return self.proxy is not None

    def run(self):
        checker = ReplyChecker()
        records = drive(account_caller(self.proxy), self.count, checker, pause=self.pause)
        summary = dict(checker.summary(), sent=self.count, answered=self.count - checker.errors,
                       records=records)
        if self.report:
            with open(self.report, 'w') as f:
                json.dump(summary, f)
        waits = [replied - sent for _, sent, replied, _ in records if replied is not None]
        print('bank_client: %(sent)d sent, %(answered)d answered, %(correct)d correct, %(lost)d lost, '
              '%(duplicated)d duplicated, %(reordered)d reordered, %(errors)d failed calls' % summary
              + ('; reply time median %.1f ms, longest %.1f ms' % (median(waits) * 1e3, max(waits) * 1e3)
                 if waits else ''), flush=True)
        return checker.summary()['correct'] == self.count
