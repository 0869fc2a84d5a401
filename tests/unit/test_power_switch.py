"""Fencing across hosts by a power switch: the spec, the request/answer, what counts as confirmed
off, the Fencing state machine (never a promotion while the peer may still answer), and a switch
agent on a Unix socket with its client (no root, no master)."""
import os
import random
import tempfile
import threading

import pytest

from aft_ftm import sites
from aft_ftm.power_switch import (EDGES, FenceState, Fencing, Outcome, SwitchError, SwitchSpec, answer_outcome,
                                  command_outcome, encode_answer, encode_request, parse_request, parse_spec)
from aft_ftm.power_switch_exec import SwitchServer, call_switch


@pytest.mark.parametrize('text, spec', [
    ('', None), ('none', None), ('  none ', None),
    ('unix:/run/aft_hosts/x.switch', SwitchSpec('unix', path='/run/aft_hosts/x.switch')),
    ('command:fence_ipmilan --ip=10.0.0.2 --action=off',
     SwitchSpec('command', argv=['fence_ipmilan', '--ip=10.0.0.2', '--action=off'])),
    ("command:fence_x -n '{host}' -o off", SwitchSpec('command', argv=['fence_x', '-n', '{host}', '-o', 'off'])),
])
def test_specs(text, spec):
    assert parse_spec(text) == spec


@pytest.mark.parametrize('text, named', [
    ('ipmi:10.0.0.2', "unknown kind 'ipmi'"), ('unix:relative/path', 'must be absolute'),
    ('command:', 'no command'), ("command:fence 'open", 'cannot split'), (3, 'give a string'),
    ('/run/x.switch', 'unknown kind'),
])
def test_bad_specs_are_refused_naming_the_problem(text, named):
    with pytest.raises(SwitchError, match=named):
        parse_spec(text)


def test_the_host_placeholder_of_a_fence_command():
    assert parse_spec('command:fence_x -n {host} --plug={host}').command_for('master') == \
        ['fence_x', '-n', 'master', '--plug=master']


def test_requests_round_trip_and_bad_ones_are_named():
    assert parse_request(encode_request('off', 'master')) == ('off', 'master')
    assert parse_request('{"op": "status", "host": "slave"}\n') == ('status', 'slave')
    for line, named in [(b'', 'empty'), (b'nonsense', 'not JSON'), (b'[1]', 'not a JSON object'),
                        (b'{"op": "reboot", "host": "a"}', "unknown op 'reboot'"), (b'{"op": "off"}', 'no host')]:
        with pytest.raises(SwitchError, match=named):
            parse_request(line)
    with pytest.raises(SwitchError):
        encode_request('off', '')


@pytest.mark.parametrize('answer, confirmed, named', [
    (encode_answer('master', True, 'off', 'link down'), True, 'master off'),
    (encode_answer('master', False, error='no such host'), False, 'refused to power master off: no such host'),
    (encode_answer('slave', True, 'off'), False, "for host 'slave'"),
    (encode_answer('master', True, 'up'), False, "'up', not off"),
    (b'', False, 'unreadably'), (b'{"ok": true', False, 'unreadably'),
    (b'{"ok": "yes", "host": "master", "state": "off"}', False, 'refused'),
])
def test_only_an_answer_that_says_this_host_is_off_confirms(answer, confirmed, named):
    outcome = answer_outcome(answer, 'master')
    assert outcome.confirmed is confirmed and named in outcome.detail


def test_a_fence_command_confirms_by_exit_status_zero_only():
    assert command_outcome(['fence_x'], 0, '', 'master').confirmed
    for code in (1, 2, -9, None):
        outcome = command_outcome(['fence_x', '-o', 'off'], code, 'Failed: Unable to connect\n', 'master')
        assert not outcome.confirmed and 'may still run' in outcome.detail and 'Unable to connect' in outcome.detail


def test_fencing_without_a_switch_allows_the_promotion():
    fencing = Fencing(None, '')
    assert fencing.may_promote()                       # the first primary: nothing to fence
    assert fencing.begin(0.0) is FenceState.NO_SWITCH and fencing.may_promote()


def test_fencing_refuses_bad_configuration():
    with pytest.raises(SwitchError, match='peer_host'):
        Fencing(SwitchSpec('unix', path='/x'), '')
    with pytest.raises(SwitchError, match='retry period'):
        Fencing(SwitchSpec('unix', path='/x'), 'master', retry_period=0)


def test_property_no_promotion_until_a_confirmation():
    """Seeded random sequences of switch outcomes and clock steps: a promotion is allowed exactly once
    an outcome confirmed the host off, never before, and retries come only after the period."""
    seed = random.randrange(1 << 30)
    rng = random.Random(seed)
    for _ in range(300):
        fencing = Fencing(SwitchSpec('unix', path='/x'), 'master', retry_period=1.0)
        now = rng.uniform(0, 100)
        assert fencing.begin(now) is FenceState.FENCING and not fencing.may_promote(), seed
        confirmed, refused_at = False, None
        for _ in range(rng.randint(1, 8)):
            if fencing.state is FenceState.FENCING:
                ok = rng.random() < 0.3
                fencing.settle(Outcome(ok, 'x'), now)
                confirmed, refused_at = confirmed or ok, now
            assert fencing.may_promote() == confirmed, seed
            step = rng.uniform(0, 2)
            assert fencing.retry_due(now + step) == (not confirmed and now + step - refused_at >= 1.0), seed
            now += step
            fencing.retry(now)
            if confirmed:
                break
        assert fencing.may_promote() == confirmed, seed
        fencing.rearm()
        assert fencing.state is FenceState.IDLE, seed


def test_every_edge_has_a_reason_and_a_late_outcome_changes_nothing():
    assert all(reason for reason in EDGES.values())
    fencing = Fencing(SwitchSpec('unix', path='/x'), 'master')
    assert fencing.settle(Outcome(True, ''), 0.0) is FenceState.IDLE and fencing.attempts == 0
    fencing.begin(0.0)
    fencing.rearm()                                   # the peer re-joined while the switch was asked
    assert fencing.settle(Outcome(True, ''), 0.1) is FenceState.IDLE


@pytest.fixture
def agent():
    directory = tempfile.mkdtemp(prefix='aft_switch_')
    state = {'master': 'up', 'slave': 'up'}
    calls = []

    def power_off(host):
        if host not in state:
            raise ValueError('no host %s' % host)
        calls.append(host)
        state[host] = 'off'
        return 'link down, then 7 processes killed'
    server = SwitchServer(os.path.join(directory, 'x.switch'), power_off, lambda host: state.get(host, 'unknown'))
    server.start()
    yield server, state, calls
    server.stop()
    assert not os.path.exists(server.path)
    os.rmdir(directory)


def test_the_agent_powers_off_once_and_answers_off(agent):
    server, state, calls = agent
    spec = parse_spec('unix:' + server.path)
    assert oct(os.stat(server.path).st_mode & 0o777) == '0o600'
    first = call_switch(spec, 'master', 2.0)
    assert first.confirmed and 'master off' in first.detail and calls == ['master']
    again = call_switch(spec, 'master', 2.0)           # already off: confirmed, not powered off twice
    assert again.confirmed and 'already off' in again.detail and calls == ['master']
    unknown = call_switch(spec, 'nobody', 2.0)
    assert not unknown.confirmed and 'no host nobody' in unknown.detail
    server.refuse('maintenance')
    refused = call_switch(spec, 'slave', 2.0)
    assert not refused.confirmed and 'maintenance' in refused.detail and state['slave'] == 'up'
    assert server.requests == [('off', 'master', True), ('off', 'master', True), ('off', 'nobody', False),
                               ('off', 'slave', False)]


def test_a_switch_that_cannot_be_reached_or_hangs_confirms_nothing(agent):
    server, _, _ = agent
    gone = call_switch(parse_spec('unix:/nonexistent/aft.switch'), 'master', 1.0)
    assert not gone.confirmed and 'cannot be reached' in gone.detail
    release = threading.Event()
    server._power_off = lambda host: release.wait(5) and 'late'
    hung = call_switch(parse_spec('unix:' + server.path), 'master', 0.3)
    release.set()
    assert not hung.confirmed and 'did not answer within 0.3 s' in hung.detail


def test_fence_commands():
    assert call_switch(parse_spec('command:true'), 'master', 5.0).confirmed
    failed = call_switch(parse_spec('command:false'), 'master', 5.0)
    assert not failed.confirmed and 'exited 1' in failed.detail
    missing = call_switch(parse_spec('command:/nonexistent/fence_x'), 'master', 5.0)
    assert not missing.confirmed and 'no such program' in missing.detail
    slow = call_switch(parse_spec('command:sleep 5'), 'master', 0.2)
    assert not slow.confirmed and 'did not finish within 0.2 s' in slow.detail
    named = call_switch(parse_spec("command:sh -c 'test \"$0\" = master' {host}"), 'master', 5.0)
    assert named.confirmed


def test_this_host_is_the_ros_name_when_set(monkeypatch):
    monkeypatch.delenv('ROS_HOSTNAME', raising=False)
    monkeypatch.delenv('ROS_IP', raising=False)
    assert sites.this_host() == os.uname()[1]
    monkeypatch.setenv('ROS_IP', '10.213.7.11')
    assert sites.this_host() == '10.213.7.11'
    monkeypatch.setenv('ROS_HOSTNAME', 'master.local')
    assert sites.this_host() == 'master.local'
