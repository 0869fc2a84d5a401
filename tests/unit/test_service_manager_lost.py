"""A service instance that ended while no service manager watched it (it died with its manager, or
while none ran) is a fault the next manager counts, as an exit, and acts on by the service's policy.
Before session 39 it was started again as if nothing had happened: a service killing its manager
each time, or dying with it, kept a fresh restart allowance and no back-off (Limits of session 38).
Not counted: a warm spare's end (never the service's work), and processes recorded under another
boot of the machine (the machine stopped, not the service). No master: the node's pid-file reading
with a real pid file and real processes."""
import os
import subprocess
import sys
import threading

import pytest

from aft_service_manager import trust
from aft_service_manager.services import Sample, State, Supervisor, parse_config

node_module = pytest.importorskip('aft_service_manager.ros.service_manager_node')

BOOT = 'this-boot'
DEAD = Sample(alive=False, exit_code=1, stopped=False, cpu_percent=0.0, rss=50e6)
GB = 1e9


def ended_process():
    """The description (pid, start time, command line) of a process that has ended."""
    import psutil
    proc = subprocess.Popen([sys.executable, '-c', 'pass'])
    described = trust.describe(psutil.Process(proc.pid))
    proc.wait(10)
    return described


@pytest.fixture
def node(tmp_path):
    n = node_module.ServiceManagerNode.__new__(node_module.ServiceManagerNode)
    n.supervisor = Supervisor(parse_config('services:\n  a: {command: x, restart_limit: 2}\n  b: {command: y}\n',
                                           source='test.yaml'))
    n.pid_file = str(tmp_path / 'm.pids')
    n.boot, n.lost = BOOT, {}
    n.unacted, n.counted, n.already_counted = {}, set(), set()
    n.children, n.spares, n.own_trees, n.instances = {}, {}, [], 0
    n.lock = threading.RLock()
    n.record_file, n.recorded, n.own = str(tmp_path / 'm.record'), None, {}
    n.published_safe, n.published_also = None, 0
    return n


def write_pids(node, **entries):
    trust.write_private_json(node.pid_file, {name: dict(entry, service=name.split(' ')[0], tree='t-' + name)
                                             for name, entry in entries.items()})


def test_an_instance_gone_since_the_last_manager_is_counted_others_are_not(node):
    write_pids(node, **{'a': dict(ended_process(), spare=False, boot=BOOT),          # died with its manager
                        'a (spare)': dict(ended_process(), spare=True, boot=BOOT),   # a spare: not its work
                        'b': dict(ended_process(), spare=False, boot='an-earlier-boot')})   # a reboot
    assert node._kill_orphans() == []
    assert sorted(node.lost) == ['a'] and 'ended while no manager watched it' in node.lost['a']


def test_a_pid_taken_by_another_process_means_the_recorded_one_ended(node):
    import psutil
    other = dict(trust.describe(psutil.Process(os.getpid())), spare=False, boot=BOOT)
    other['create_time'] -= 1000.0   # recorded earlier than this process began
    write_pids(node, a=other)
    node._kill_orphans()
    assert sorted(node.lost) == ['a'] and 'another process now' in node.lost['a']


def test_a_machine_whose_boot_cannot_be_told_counts_nothing(node):
    node.boot = ''
    write_pids(node, a=dict(ended_process(), spare=False, boot=''))
    node._kill_orphans()
    assert node.lost == {}


def decide(sup, lost, now, act=lambda decision: None):
    """What the node's set-up does: every lost one taken as started, then each decided and acted on."""
    decisions = []
    for name in sup.take_as_started(lost, now):
        decision = sup.ended_unwatched(name, lost[name], now)
        if decision is not None:
            decisions.append(decision)
            act(decision)
    return decisions


def test_the_lost_instance_is_acted_on_as_an_exit_within_the_restart_limit(node, monkeypatch):
    """Counted as an exit, the service is restarted by its policy; once the restart limit (restored
    from the record) is exhausted, it is FAILED and the safe state is escalated, as under one manager."""
    acted = []
    monkeypatch.setattr(node, '_act', lambda decision, now: acted.append(decision), raising=False)
    monkeypatch.setattr(node, '_event', lambda *a, **k: None, raising=False)
    [decision] = decide(node.supervisor, {'a': 'pid 1 is gone: it ended while no manager watched it'}, 10.0)
    node._fault(decision, 10.0)
    s = node.supervisor['a']
    assert dict(s.errors) == {'exit': 1} and s.state == State.RESTARTING and len(s.restarts) == 1
    assert acted[-1].escalate is None
    s.restarts.append(s.clock(10.5))   # a second restart within the window (from the record, say)
    s.spawned(10.6)
    node._fault(node.supervisor.fault('a', 'exit', 'again', 11.0), 11.0)
    assert s.state == State.FAILED and 'restart limit exhausted' in acted[-1].escalate


@pytest.mark.parametrize('seed', [int(os.environ.get('AFT_SEED', 0)) or s for s in range(3901, 3911)])
def test_a_back_off_hold_under_way_when_the_manager_dies_is_resumed_to_its_end(seed):
    """A service in its back-off hold (restarted after a delay) when its manager dies: the next
    manager started it at once (Limits of session 38), so a crash loop that kills its manager ran
    without back-off. Now the record carries the hold's end, and the restart comes when it would
    have under one manager. Faults and the moment of the manager's death are drawn from the seed."""
    import json
    import random
    rng = random.Random(seed)
    c = parse_config('services:\n  a: {command: x, restart_limit: 10, restart_window: 60, restart_delay: 0.5, '
                     'restart_delay_factor: 2, restart_delay_max: 4, stable_after: 100}\n', source='test.yaml')
    sup, now = Supervisor(c), 1000.0
    faults = rng.randint(1, 4)
    for fault in range(faults):
        sup['a'].spawned(now)
        sup['a'].heard(now + 0.01, 'ok')
        now += rng.uniform(0.1, 1.0)
        sup.check('a', DEAD, now, GB)
        due_at = sup.next_due()
        assert due_at is not None and due_at > now, 'seed %d: no back-off hold' % seed
        died = now + rng.uniform(0.0, 0.99) * (due_at - now)   # the manager dies during the hold
        if fault == faults - 1:
            break
        now = due_at
        assert sup.due(now) == [('spawn', 'a')]
    record = json.loads(json.dumps(sup.record()))
    again = Supervisor(c)
    assert again.restore(record, died) == [], 'seed %d' % seed
    assert again['a'].state == State.RESTARTING, 'seed %d: %s' % (seed, again['a'].state)
    assert again.next_due() == pytest.approx(due_at), 'seed %d: the hold did not resume to its end' % seed
    assert again.due(died) == [] and again.due(due_at) == [('spawn', 'a')], 'seed %d' % seed


def test_a_resumed_hold_never_exceeds_the_longest_back_off():
    """A hold's end far ahead (the monotonic clock started again at a reboot) holds at most
    restart_delay_max; one already past resumes nothing (the service starts at once)."""
    c = parse_config('services:\n  a: {command: x, restart_delay: 1, restart_delay_max: 4}\n', source='test.yaml')
    far = {'safe_state': None, 'down': {}, 'counts': {'a': {'errors': {'exit': 1}, 'consecutive': 1,
                                                            'restarts': [5.0], 'hold_until': 1e9}}}
    sup = Supervisor(c)
    sup.restore(far, 10.0)
    assert sup.next_due() == pytest.approx(14.0)
    past = json_copy(far)
    past['counts']['a']['hold_until'] = 9.0
    sup = Supervisor(c)
    sup.restore(past, 10.0)
    assert sup.next_due() is None and sup['a'].state == State.STOPPED


def json_copy(data):
    import json
    return json.loads(json.dumps(data))


@pytest.mark.parametrize('bad', ['soon', float('nan'), True, [1.0]])
def test_a_malformed_hold_in_the_record_is_refused(bad):
    from aft_service_manager.services import ServiceConfigError
    c = parse_config('services:\n  a: {command: x}\n', source='test.yaml')
    with pytest.raises(ServiceConfigError, match='counts.a'):
        Supervisor(c).restore({'down': {}, 'counts': {'a': {'hold_until': bad}}}, 10.0)


def test_a_lost_service_its_policy_leaves_stopped_stays_down_in_the_record(node):
    """Review of session 39: its start was not counted, so record() left the stopped service out and
    the next manager autostarted it, undoing the policy."""
    node.supervisor = Supervisor(parse_config('services:\n  a: {command: x, on_failure: terminate}\n',
                                              source='test.yaml'))
    [decision] = decide(node.supervisor, {'a': 'pid 7 is gone'}, 1.0)
    assert node.supervisor['a'].state == State.STOPPED and ('kill', 'a') in decision.actions
    assert 'a' in node.supervisor.record()['down']


def test_entries_a_clean_stop_marked_malformed_or_odd_ones_are_not_counted(node):
    write_pids(node, a=dict(ended_process(), spare=False, boot=BOOT, stopping=True))   # its manager stopped it
    node._kill_orphans()
    broken = {'a': {'pid': 999999, 'service': 'a', 'boot': BOOT},                       # no start time
              'b': dict(ended_process(), service=['b'], boot=BOOT)}                     # not a name
    trust.write_private_json(node.pid_file, broken)
    node._kill_orphans()
    assert node.lost == {}


def test_a_clean_stop_marks_the_instances_it_stops_before_any_signal(node):
    import psutil

    class Child(object):
        proc, spare, ready, handle, slot, instance = psutil.Process(os.getpid()), False, True, 't-a', None, 1

        def alive(self):
            return True
    node.children, node.own = {'a': Child()}, {}
    node._record_pids(stopping=True)
    entry = trust.read_private_json(node.pid_file)['a']
    assert entry['stopping'] is True and entry['boot'] == BOOT and trust.well_formed(entry)


class Acts(object):
    """The node's actions on the children, faked: who runs after each decision is acted on."""

    def __init__(self, sup):
        self.sup, self.running = sup, set()

    def __call__(self, decision):
        for verb, name in decision.actions:
            if verb == 'kill':
                self.running.discard(name)
            elif verb == 'spawn' and self.sup.may_spawn(name, 0.0):
                self.sup[name].spawned(5.0)
                self.running.add(name)


@pytest.mark.parametrize('order', ['a first', 'b first'])
@pytest.mark.parametrize('limit', [0, 3])
def test_two_lost_services_one_terminated_with_the_other_end_the_same_whatever_the_order(order, limit):
    """Reviews of session 39: A lists B in terminate_with, both found ended. Decided one by one, B's
    fault restarted it after A's (B still in its initial STOPPED) had skipped it, and B ran without
    A, depending on the order of the configuration; decided all first, then acted on, B was spawned
    from a stale decision, killed by A's, and left STARTING with no process for ever. Now all are
    taken as started, then each is decided and acted on in turn: B ends stopped with A, with no
    process and a state that says so, in either order; A's policy decides A."""
    a = '  a: {command: x, terminate_with: [b], restart_limit: %d}\n' % limit
    b = '  b: {command: y}\n'
    sup = Supervisor(parse_config('services:\n' + (a + b if order == 'a first' else b + a), source='test.yaml'))
    acts = Acts(sup)
    decide(sup, {'a': 'pid 1 is gone', 'b': 'pid 2 is gone'}, 5.0, acts)
    assert sup['b'].state == State.STOPPED and 'b' not in acts.running, (order, sup['b'].state, acts.running)
    assert sup['a'].state == (State.FAILED if limit == 0 else State.STARTING), order
    assert ('a' in acts.running) == (limit > 0)


def test_a_service_that_must_not_run_without_a_lost_one_now_down_is_not_started():
    """Review of session 39: it was autostarted, ran without the lost service, then was killed."""
    sup = Supervisor(parse_config('services:\n  l: {command: x, terminate_with: [d], restart_limit: 0}\n'
                                  '  d: {command: y, terminate_with: [e]}\n  e: {command: z}\n'
                                  '  r: {command: w, restart_delay: 2, restart_with: [q]}\n  q: {command: v}\n'
                                  '  free: {command: u}\n', source='test.yaml'))
    lost = {'l': 'pid 1 is gone', 'r': 'pid 3 is gone'}
    sup['r'].consecutive = 1   # its back-off holds its restart
    decide(sup, lost, 5.0)
    assert sup['l'].state == State.FAILED and sup['r'].state == State.RESTARTING and sup['r'].spawn_at > 5.0
    verbs = {n: sup.starts_after_lost(n, lost, 5.0)[0] for n in sup.order if n not in lost}
    assert verbs == {'d': 'skip', 'e': 'skip', 'q': 'held', 'free': 'spawn'}, verbs
    assert sup['d'].held_down and 'terminated with l' in sup['d'].reason
    assert 'd' in sup.record()['down'] and sup.due(sup['r'].spawn_at + 1.0) == [('spawn', 'r'), ('spawn', 'q')]


def test_an_instance_a_clean_stop_was_ending_is_killed_not_adopted_nor_counted(node):
    """Review of session 39: its manager killed in the middle of its stop, the next one adopted the
    instance still handling its SIGTERM, then counted its exit as a fault."""
    import psutil
    proc = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'], start_new_session=True)
    try:
        entry = dict(trust.describe(psutil.Process(proc.pid)), spare=False, boot=BOOT, stopping=True)
        write_pids(node, a=entry)
        assert node._kill_orphans() == [] and node.lost == {} and node.children == {}
        assert proc.wait(10) is not None   # killed
    finally:
        proc.kill()
        proc.wait(10)


def test_a_critical_service_not_started_for_a_lost_one_escalates():
    """Review of session 39: skipped, it stayed down with no safe state (one manager escalates)."""
    sup = Supervisor(parse_config('services:\n  l: {command: x, terminate_with: [c], on_failure: terminate}\n'
                                  '  c: {command: y, critical: true}\n', source='test.yaml'))
    decide(sup, {'l': 'pid 1 is gone'}, 5.0)
    assert sup.starts_after_lost('c', {'l': 'pid 1 is gone'}, 5.0)[0] == 'skip'
    assert sup.safe_state and 'c (critical)' in sup.safe_state


def test_a_chain_restarted_with_a_lost_service_is_held_in_dependency_order():
    """Review of session 39: l restart_with [m], m restart_with [q], configured q, m, l, l lost with a
    back-off: q was spawned before m and l, running against services not there."""
    sup = Supervisor(parse_config('services:\n  q: {command: a}\n  m: {command: b, restart_with: [q]}\n'
                                  '  l: {command: c, restart_with: [m], restart_delay: 1}\n', source='test.yaml'))
    sup['l'].consecutive = 1
    lost = {'l': 'pid 1 is gone'}
    decide(sup, lost, 5.0)
    verbs = [(n, sup.starts_after_lost(n, lost, 5.0)[0]) for n in sup.order if n not in lost]
    assert verbs == [('m', 'held'), ('q', 'held')], verbs
    at = sup['l'].spawn_at
    assert sup.due(at - 0.01) == [] and sup.due(at) == [('spawn', 'l'), ('spawn', 'm'), ('spawn', 'q')]


def test_a_lost_service_restarted_with_another_lost_one_is_not_faulted_again():
    """Review of session 39: lost a restart_with [b], b lost too, no delay: a's restart restarted and
    spawned b, and b's own decision then took the fresh instance for the one found ended: a second
    exit counted, the new instance killed and restarted."""
    sup = Supervisor(parse_config('services:\n  a: {command: x, restart_with: [b]}\n  b: {command: y}\n',
                                  source='test.yaml'))
    acts = Acts(sup)
    decisions = decide(sup, {'a': 'pid 1 is gone', 'b': 'pid 2 is gone'}, 5.0, acts)
    assert [d.service for d in decisions] == ['a'] and acts.running == {'a', 'b'}
    assert dict(sup['b'].errors) == {} and sup['b'].starts == 2 and sup['b'].state == State.STARTING


def successor(node):
    """The next manager of the same name, on the same files (its predecessor killed at that moment): its
    record restored and the pid file read, as its set-up begins."""
    n = node_module.ServiceManagerNode.__new__(node_module.ServiceManagerNode)
    n.__dict__.update({k: v for k, v in node.__dict__.items() if k in ('pid_file', 'record_file', 'boot', 'lock')})
    n.supervisor = Supervisor(node.supervisor.config)
    n.lost, n.unacted, n.counted, n.already_counted = {}, {}, set(), set()
    n.children, n.spares, n.own_trees, n.instances, n.own, n.recorded = {}, {}, [], 0, {}, None
    n.published_safe, n.published_also = None, 0
    n._restore()
    n._kill_orphans()
    return n


class Died(Exception):
    """The manager killed at that instant (nothing after it runs)."""


def set_up(node, monkeypatch, die_at=None, fail_writes=()):
    """The set-up's steps with the lost instances (_take_lost, then _act_on_lost), the manager killed at
    its die_at-th fault (None: never); a fault restarting a service rewrites the pid file, as a spawn does.
    fail_writes: the paths whose writes fail (a full disk)."""
    faults = []
    writes = trust.write_private_json

    def write(path, data):
        if path in fail_writes:
            raise OSError(28, 'No space left on device')
        return writes(path, data)
    monkeypatch.setattr(trust, 'write_private_json', write)
    for name in ('logerr_throttle', 'logwarn_throttle'):   # (rospy's throttle needs ROS time)
        monkeypatch.setattr(node_module.rospy, name, lambda *a, **k: None)

    def fault(decision, now):
        faults.append(decision.service)
        node._record_pids()
        if die_at is not None and len(faults) == die_at:
            raise Died()
    monkeypatch.setattr(node, '_fault', fault)
    try:
        node._act_on_lost(node._take_lost([]), 10.0)
    except Died:
        pass
    monkeypatch.setattr(trust, 'write_private_json', writes)
    return faults


def two_lost(node):
    write_pids(node, a=dict(ended_process(), spare=False, boot=BOOT), b=dict(ended_process(), spare=False, boot=BOOT))
    node._kill_orphans()
    assert sorted(node.lost) == ['a', 'b']


def counted(manager):
    return {n: dict(manager.supervisor[n].errors) for n in ('a', 'b')}


@pytest.mark.parametrize('die_at', [1, 2, None])
def test_a_manager_killed_in_its_set_up_leaves_each_loss_to_the_next_exactly_once(node, monkeypatch, die_at):
    """Limits of session 39: the set-up wrote the pid file again without the lost instances before their
    faults reached the record, so a manager killed in between forgot them, and the next one started the
    services with their counts untouched. Now a lost instance stays in the pid file until the record
    counts it, and the record names what it counted until the pid file forgot it. Killed after its
    first fault, its second, or never: each loss is counted once, by it or by its successor."""
    two_lost(node)
    faults = set_up(node, monkeypatch, die_at)
    after = successor(node)
    have = counted(after)
    assert faults[:die_at] == faults and set(faults) <= {'a', 'b'}
    for name in ('a', 'b'):
        by_the_record = have[name] == {'exit': 1}
        assert by_the_record == (name in faults) and by_the_record != (name in after.lost), (name, have, after.lost)
    if die_at is None:
        assert trust.read_private_json(node.pid_file) == {}
        assert 'lost_counted' not in trust.read_private_json(node.record_file)   # forgotten with the pid file's


def test_a_manager_killed_before_it_counted_anything_leaves_every_loss_named(node, monkeypatch):
    two_lost(node)
    node._take_lost([])                     # its pid file written again: the losses still named
    after = successor(node)
    assert sorted(after.lost) == ['a', 'b'] and counted(after) == {'a': {}, 'b': {}}


def test_three_managers_killed_in_turn_count_each_loss_once(node, monkeypatch):
    """M1 counts a and is killed; M2 finds b only, counts it and is killed before its pid file forgot
    b; M3 finds nothing, and holds both counts."""
    two_lost(node)
    first = set_up(node, monkeypatch, die_at=1)
    m2 = successor(node)
    assert sorted(m2.lost) == sorted({'a', 'b'} - set(first))
    second = set_up(m2, monkeypatch, die_at=1)
    m3 = successor(m2)
    assert sorted(first + second) == ['a', 'b'] and m3.lost == {} and counted(m3) == {'a': {'exit': 1}, 'b': {'exit': 1}}


@pytest.mark.parametrize('failing', ['record', 'pid file'])
def test_a_write_that_fails_in_the_set_up_never_loses_a_loss_nor_counts_it_twice(node, monkeypatch, failing):
    """Review of session 40: the entry left the pid file although the record could not be written (a
    loss never counted), or the record forgot what it counted although the pid file still named it (a
    loss counted twice)."""
    two_lost(node)
    path = node.record_file if failing == 'record' else node.pid_file
    faults = set_up(node, monkeypatch, fail_writes=(path,))
    assert sorted(faults) == ['a', 'b']
    after = successor(node)
    have = counted(after)
    for name in ('a', 'b'):
        assert (have[name] == {'exit': 1}) != (name in after.lost), (name, have, after.lost)


@pytest.mark.parametrize('counted_first', [0, 1])
def test_a_clean_stop_in_the_set_up_keeps_the_losses_not_yet_counted(node, monkeypatch, counted_first):
    """Review of session 40: a clean stop (SIGINT) in the set-up removed the pid file, with the losses
    not yet counted in it. The whole shutdown() runs here (no service, no master)."""
    import types
    two_lost(node)
    faults = set_up(node, monkeypatch, die_at=counted_first) if counted_first else []
    if not counted_first:
        node._take_lost([])
    node.stopping, node.programs, node.local, node.config = {}, None, None, {'manager': {'kill_timeout': 0.1}}
    node.safe_pub = types.SimpleNamespace(publish=lambda msg: None)
    node.tree = types.SimpleNamespace(leftovers=lambda: [], close=lambda timeout: None)
    monkeypatch.setattr(node, '_wake', lambda: None, raising=False)
    monkeypatch.setattr(node_module.rospy.Time, 'now', staticmethod(lambda: node_module.rospy.Time(0)))
    node.shutdown()
    after = successor(node)
    have = counted(after)
    assert len(faults) == counted_first
    for name in ('a', 'b'):
        assert (have[name] == {'exit': 1}) != (name in after.lost), (name, have, after.lost)


def test_a_malformed_list_of_counted_losses_in_the_record_counts_nothing_as_counted():
    for record in ({'lost_counted': 3}, {'lost_counted': [['a', 'x', 1.0], ['a']]}, None, [], {'lost_counted': None}):
        assert node_module._counted_lost(record) == set()
    assert node_module._counted_lost({'lost_counted': [['a', 12, 3.25]]}) == {('a', 12, 3.25)}


class Writes(object):
    """trust.write_private_json, the manager killed (Died) in place of its die_at-th write (None: never),
    or right after it (``after``)."""

    def __init__(self, monkeypatch, die_at=None, after=False):
        self.real, self.die_at, self.after, self.paths = trust.write_private_json, die_at, after, []
        monkeypatch.setattr(trust, 'write_private_json', self)

    def __call__(self, path, data):
        if self.die_at is not None and len(self.paths) + 1 == self.die_at and not self.after:
            raise Died()
        self.paths.append(path)
        written = self.real(path, data)
        if self.after and len(self.paths) == self.die_at:
            raise Died()
        return written


def running(node, monkeypatch, config, ends=True):
    """node running service a (a real process, its Child), its pid file and record on disk; a's process
    then exits (unless not ``ends``: it hangs). The kill and spawn actions as the node's, without
    signals: the pid file written."""
    node.supervisor = Supervisor(parse_config(config, source='test.yaml'))
    for name in ('logerr_throttle', 'logwarn_throttle', 'logwarn', 'logerr', 'loginfo'):
        monkeypatch.setattr(node_module.rospy, name, lambda *a, **k: None)
    monkeypatch.setattr(node, '_event', lambda *a, **k: None, raising=False)
    monkeypatch.setattr(node, '_publish_safe_state', lambda: None, raising=False)
    monkeypatch.setattr(node, '_publish_diagnostics', lambda: None, raising=False)
    started = []

    def start():
        proc = subprocess.Popen([sys.executable, '-c', 'import sys; sys.stdin.read()'], stdin=subprocess.PIPE,
                                start_new_session=True)
        started.append(proc)
        return node_module.Child(proc, 10.0)

    def act_one(verb, name, decision, now):
        if verb == 'kill':
            child = node.children.pop(name, None)
            if child is not None and child.alive():
                child.popen.kill()
                child.popen.wait(10)
            node._record_pids()
        elif verb == 'spawn':
            node.children[name] = start()
            node._record_pids()
            node.supervisor[name].spawned(now)
    monkeypatch.setattr(node, '_act_one', act_one, raising=False)
    node.children['a'] = start()
    node.supervisor['a'].spawned(1.0)
    node._record_pids()
    node._sync_safe_state()
    if ends:
        started[0].stdin.close()
        started[0].wait(10)
    return started


@pytest.mark.parametrize('config', ['services:\n  a: {command: x, restart_limit: 2, restart_delay: 0}\n',
                                    'services:\n  a: {command: x, restart_limit: 0, critical: true}\n'])
def test_a_fault_is_counted_once_wherever_its_manager_is_killed_while_acting_on_it(node, monkeypatch, config):
    """Review of session 40: a fault's actions wrote the pid file (the ended instance gone, its
    replacement named) before the record counted the fault, so a manager killed in between left the
    exit counted nowhere (a fresh allowance) and a critical service's escalation unsaid. Killed in
    place of each of the writes acting on the fault makes, or never: the next manager counts the exit
    exactly once (in the record, or finding the instance ended), and holds the safe state it escalated."""
    started = running(node, monkeypatch, config)
    try:
        decision = node.supervisor.fault('a', 'exit', 'exit code 0', 5.0)
        writes = Writes(monkeypatch)
        node._fault(decision, 5.0)
        count = len(writes.paths)
        assert count >= 3 and node.pid_file in writes.paths and node.record_file in writes.paths
        escalated = node.supervisor.safe_state
        assert (escalated is not None) == ('critical' in config)
        for die_at in range(1, count + 2):
            fresh = node_module.ServiceManagerNode.__new__(node_module.ServiceManagerNode)
            fresh.__dict__.update(node.__dict__)
            fresh.children, fresh.counted, fresh.recorded = {}, set(), None
            started.extend(running(fresh, monkeypatch, config))   # the same start again, on the same files
            writes = Writes(monkeypatch, die_at)
            try:
                fresh._fault(fresh.supervisor.fault('a', 'exit', 'exit code 0', 5.0), 5.0)
            except Died:
                pass
            monkeypatch.setattr(trust, 'write_private_json', writes.real)
            after = successor(fresh)
            exits = after.supervisor['a'].errors.get('exit', 0) + (1 if 'a' in after.lost else 0)
            assert exits == 1, (die_at, writes.paths, dict(after.supervisor['a'].errors), after.lost)
            if escalated and 'a' not in after.lost:   # counted by the record: its escalation with it
                assert after.supervisor.safe_state is not None, die_at
    finally:
        for proc in started:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)


def test_an_infinite_number_in_the_record_or_the_pid_file_is_malformed_not_a_crash_at_every_start(node):
    """Review of session 40: JSON reads Infinity and 1e999 as inf, int() of which raised OverflowError,
    caught nowhere: the manager crashed at each start on such a file."""
    assert node_module._counted_lost({'lost_counted': [['a', float('inf'), 1.0], ['a', 12, 3.25]]}) == {('a', 12, 3.25)}
    entry = dict(ended_process(), spare=False, boot=BOOT)
    assert trust.well_formed(dict(entry, pid=float('inf'))) is False
    with open(node.pid_file, 'w') as f:   # as a corrupted file would hold it
        f.write('{"a": {"pid": Infinity, "create_time": 1.0, "cmdline": ["x"], "service": "a", "tree": "t", '
                '"spare": false, "boot": "%s"}, "b": {"pid": 1e999, "create_time": 1.0, "cmdline": [], '
                '"service": "b", "tree": "t", "spare": false, "boot": "%s"}}' % (BOOT, BOOT))
    os.chmod(node.pid_file, 0o600)
    assert node._kill_orphans() == [] and node.lost == {}


def test_a_clean_stop_before_the_first_pid_file_write_marks_what_it_adopted_and_keeps_the_losses(node, monkeypatch):
    """Review of session 40: the pid file became this manager's own only at its first write, after the
    adoption. Stopped cleanly (SIGINT) in between, it stopped the instances it had adopted and left the
    predecessor's file unmarked: the next manager counted each of them as a fault."""
    import psutil
    import types
    live = subprocess.Popen([sys.executable, '-c', 'import sys; sys.stdin.read()'], stdin=subprocess.PIPE,
                            start_new_session=True)
    try:
        write_pids(node, a=dict(ended_process(), spare=False, boot=BOOT),
                   b=dict(trust.describe(psutil.Process(live.pid)), spare=False, boot=BOOT))

        def adopt(name, entry, proc, now):   # as _adopt does, without the tree's checks
            node.children[entry['service']] = node_module.Child(live, 10.0)
            node.supervisor[entry['service']].spawned(now)
            return True
        monkeypatch.setattr(node, '_adopt', adopt)
        monkeypatch.setattr(node, '_event', lambda *a, **k: None, raising=False)
        assert node._kill_orphans() == ['t-b'] and sorted(node.lost) == ['a']
        node.stopping, node.programs, node.local, node.config = {}, None, None, {'manager': {'kill_timeout': 2.0}}
        node.safe_pub = types.SimpleNamespace(publish=lambda msg: None)
        node.tree = types.SimpleNamespace(leftovers=lambda: [], close=lambda timeout: None)
        monkeypatch.setattr(node, '_wake', lambda: None, raising=False)
        monkeypatch.setattr(node_module.rospy.Time, 'now', staticmethod(lambda: node_module.rospy.Time(0)))
        node.shutdown()                       # the SIGINT, before _take_lost wrote the pid file
        assert live.poll() is not None        # b stopped by this clean stop
        after = successor(node)
        assert sorted(after.lost) == ['a'], after.lost   # a's loss kept; b's end was no fault
    finally:
        if live.poll() is None:
            live.kill()
        live.wait(10)


def test_an_operator_s_stop_under_way_when_the_manager_dies_is_finished_by_the_next_one(node, monkeypatch):
    """Review of session 40: an instance an operator was stopping was named in the pid file as active:
    a manager killed before it ended left the next one to adopt it (the stop undone), and to count
    its later end as a fault. It is marked stopping now: the next manager ends it, counts nothing."""
    import psutil
    live = subprocess.Popen([sys.executable, '-c', 'import signal, sys; signal.signal(signal.SIGTERM, signal.SIG_IGN); '
                             'sys.stdin.read()'], stdin=subprocess.PIPE, start_new_session=True)
    try:
        node.stopping = {'a': node_module.Child(live, 10.0)}   # its SIGTERM ignored; the SIGKILL thread died
        node.supervisor['a'].spawned(1.0)
        assert node._record_pids()
        entry = trust.read_private_json(node.pid_file)['a (stopping)']
        assert entry['stopping'] is True and entry['pid'] == live.pid
        monkeypatch.setattr(node_module.ServiceManagerNode, '_adopt',
                            lambda *a: pytest.fail('an instance being stopped was adopted'))
        after = successor(node)
        assert after.lost == {} and after.children == {}
        live.wait(10)   # ended by the next manager (SIGKILL to its process group)
        assert not psutil.pid_exists(live.pid) or psutil.Process(live.pid).status() == psutil.STATUS_ZOMBIE
    finally:
        if live.poll() is None:
            live.kill()
        live.wait(10)


def test_a_hung_instance_whose_fault_was_counted_is_ended_by_the_next_manager_not_adopted(node, monkeypatch):
    """Review of session 40: a hung instance whose fault the record counted, its manager killed before
    the kill, was adopted by the next manager and counted again once its hang was seen again. The
    record names it (lost_counted) until it is killed: the next manager ends it instead."""
    config = 'services:\n  a: {command: x, restart_limit: 5, restart_delay: 0}\n'
    started = running(node, monkeypatch, config, ends=False)
    try:
        writes = Writes(monkeypatch)
        node._fault(node.supervisor.fault('a', 'heartbeat', 'no beat for 1 s', 5.0), 5.0)
        count = len(writes.paths)
        monkeypatch.setattr(trust, 'write_private_json', writes.real)
        for die_at, at_end in [(k, a) for k in range(1, count + 2) for a in (False, True)]:
            fresh = node_module.ServiceManagerNode.__new__(node_module.ServiceManagerNode)
            fresh.__dict__.update(node.__dict__)
            fresh.children, fresh.counted, fresh.recorded = {}, set(), None
            started.extend(running(fresh, monkeypatch, config, ends=False))
            hung = fresh.children['a'].popen
            writes = Writes(monkeypatch, die_at, at_end)
            try:
                fresh._fault(fresh.supervisor.fault('a', 'heartbeat', 'no beat for 1 s', 5.0), 5.0)
            except Died:
                pass
            monkeypatch.setattr(trust, 'write_private_json', writes.real)
            adopted = []
            monkeypatch.setattr(node_module.ServiceManagerNode, '_adopt',
                                lambda self, name, entry, proc, now: adopted.append(entry['pid']) or True)
            after = successor(fresh)
            counted = after.supervisor['a'].errors.get('heartbeat', 0)
            if hung.pid in adopted:   # not counted yet: adopted, its hang to be seen again
                assert counted == 0, (die_at, at_end, writes.paths)
            else:                     # counted: ended, by its manager or the next one
                assert counted == 1, (die_at, at_end, writes.paths, adopted)
                hung.wait(10)
            monkeypatch.undo()
            for name in ('logerr_throttle', 'logwarn_throttle', 'logwarn', 'logerr', 'loginfo'):
                monkeypatch.setattr(node_module.rospy, name, lambda *a, **k: None)
    finally:
        for proc in started:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)


def test_a_loss_whose_record_write_failed_stays_named_when_its_service_is_restarted(node, monkeypatch):
    """Review of session 40: a lost instance stayed in the pid file under its service's name until the
    record counted it; the record's write failed, the service was restarted by its policy, and the new
    instance, under the same name, hid the loss in every pid file written after: a manager killed then
    left it counted nowhere. It has a key of its own now."""
    two_lost(node)
    started = []
    writes = trust.write_private_json

    def write(path, data):
        if path == node.record_file:
            raise OSError(28, 'No space left on device')
        return writes(path, data)
    monkeypatch.setattr(trust, 'write_private_json', write)
    for name in ('logerr_throttle', 'logwarn_throttle'):
        monkeypatch.setattr(node_module.rospy, name, lambda *a, **k: None)

    def fault(decision, now):   # the policy restarts it: a new instance under its name, the pid file written
        proc = subprocess.Popen([sys.executable, '-c', 'import sys; sys.stdin.read()'], stdin=subprocess.PIPE)
        started.append(proc)
        node.children[decision.service] = node_module.Child(proc, 10.0)
        node._record_pids()
    monkeypatch.setattr(node, '_fault', fault)
    try:
        node._act_on_lost(node._take_lost([]), 10.0)
        monkeypatch.setattr(trust, 'write_private_json', writes)
        named = trust.read_private_json(node.pid_file)
        assert sorted(named) == ['a', 'a (lost)', 'b', 'b (lost)'], sorted(named)
        by_pid = {proc.pid: proc for proc in started}

        def adopt(self, name, entry, proc, now):   # the running ones: adopted, as _adopt does
            self.children[entry['service']] = node_module.Child(by_pid[proc.pid], 10.0)
            self.supervisor[entry['service']].spawned(now)
            return True
        monkeypatch.setattr(node_module.ServiceManagerNode, '_adopt', adopt)
        after = successor(node)
        assert sorted(after.lost) == ['a', 'b'] and sorted(after.children) == ['a', 'b']
        assert after._take_lost([]) == {}                       # nothing to start: both run
        assert counted(after) == {'a': {'exit': 1}, 'b': {'exit': 1}}   # each loss counted, once, here
        assert all(len(after.supervisor[n].restarts) == 1 for n in ('a', 'b'))   # with the restart it had
        third = successor(after)                                # and not again by the next one
        assert third.lost == {} and counted(third) == {'a': {'exit': 1}, 'b': {'exit': 1}}
    finally:
        for proc in started:
            proc.kill()
            proc.wait(10)
