"""rosrun aft_ftm rejoin, with the witness faked: no ROS master."""
import types

import pytest

from aft_ftm.ros import rejoin_command


@pytest.fixture(autouse=True)
def site_params(monkeypatch):
    """The parameter server: each site's Recovery's ~witness (rejoin's default witness)."""
    params = {'/master/recovery/witness': '/aft/witness/request'}
    monkeypatch.setattr(rejoin_command.rospy, 'get_param', lambda name, default=None: params.get(name, default))
    monkeypatch.setattr(rejoin_command.rospy, 'init_node', lambda *a, **k: None)
    for name in ('AFT_TLS_DIR', 'AFT_TLS_PARTY', 'AFT_TLS_POLICY'):
        monkeypatch.delenv(name, raising=False)
    return params


def test_a_launch_asked_for_the_witnesss_primary_is_refused_as_a_failure_not_an_exit_0(monkeypatch, capsys):
    """Review of the witness (session 33): right after the primary failed (before its peer's verdict),
    `rejoin SITE --launch ...` printed "nothing to re-join", exited 0 and started nothing."""
    monkeypatch.setattr(rejoin_command.rospy, 'wait_for_service', lambda service, timeout: None)
    monkeypatch.setattr(rejoin_command, 'status',
                        lambda service: types.SimpleNamespace(epoch=7, primary='master', backup='slave'))
    started = []
    monkeypatch.setattr(rejoin_command.subprocess, 'Popen', lambda *a, **k: started.append(a))
    assert rejoin_command.main(['master', '--launch', 'roslaunch x y.launch']) == 1
    assert started == [] and 'not launched' in capsys.readouterr().err
    assert rejoin_command.main(['master']) == 0     # without --launch: nothing to re-join, as before


def test_with_takeover_a_launch_waits_for_the_backup_to_take_over_and_never_launches_a_primary(monkeypatch, capsys):
    """Review of session 33: `rejoin SITE --launch` right after SITE failed, before its peer's verdict,
    could only refuse (exit 1, run it again later). With --takeover it waits for the witness to name
    another primary, then launches; a primary that never stops being one is never launched."""
    monkeypatch.setattr(rejoin_command.rospy, 'wait_for_service', lambda service, timeout: None)
    monkeypatch.setattr(rejoin_command.time, 'sleep', lambda s: None)
    answers = [('master', 'slave', 7)] * 3 + [('slave', '', 8)] * 2 + [('slave', 'master', 9)]
    asked = []

    def status(service):
        asked.append(service)
        primary, backup, epoch = answers[min(len(asked), len(answers)) - 1]
        return types.SimpleNamespace(epoch=epoch, primary=primary, backup=backup)
    monkeypatch.setattr(rejoin_command, 'status', status)
    started = []
    monkeypatch.setattr(rejoin_command.subprocess, 'Popen', lambda *a, **k: started.append(a[0]))
    assert rejoin_command.main(['master', '--launch', 'roslaunch x y.launch', '--takeover', '30']) == 0
    assert started == [['roslaunch', 'x', 'y.launch']] and len(asked) >= 5   # launched after slave took over
    # a primary that stays the primary: nothing launched, exit 1
    answers[:] = [('master', 'slave', 7)]
    asked.clear(), started.clear()
    clock = iter(range(0, 1000, 5))
    monkeypatch.setattr(rejoin_command.time, 'monotonic', lambda: next(clock))
    assert rejoin_command.main(['master', '--launch', 'roslaunch x y.launch', '--takeover', '30']) == 1
    assert started == [] and 'not launched' in capsys.readouterr().err


def test_the_witness_asked_is_the_one_the_site_s_recovery_follows(monkeypatch, site_params, capsys):
    """Review of session 40: with two services on one master, `rejoin nav_a --launch` asked the default
    witness (the bank's), which never names nav_a primary: a site still serving was launched over."""
    monkeypatch.setattr(rejoin_command.rospy, 'wait_for_service', lambda service, timeout: None)
    asked = []

    def status(service):
        asked.append(service)
        return types.SimpleNamespace(epoch=3, primary='nav_a', backup='nav_b')
    monkeypatch.setattr(rejoin_command, 'status', status)
    started = []
    monkeypatch.setattr(rejoin_command.subprocess, 'Popen', lambda *a, **k: started.append(a))
    site_params['/nav_a/recovery/witness'] = '/nav/witness/request'
    assert rejoin_command.main(['nav_a', '--launch', 'roslaunch x y.launch']) == 1   # still its primary
    assert set(asked) == {'/nav/witness/request'} and started == []
    asked.clear()
    assert rejoin_command.main(['nav_a', '--witness', '/other/witness/request']) == 0 and asked == ['/other/witness/request']
    asked.clear()
    monkeypatch.setattr(rejoin_command.time, 'sleep', lambda s: None)
    assert rejoin_command.main(['ghost', '--timeout', '0']) == 1 and asked == ['/aft/witness/request']   # the default
    site_params['/lone/recovery/witness'] = ''
    asked.clear()
    assert rejoin_command.main(['lone', '--launch', 'x']) == 2 and asked == [] and started == []
    assert 'follows no witness' in capsys.readouterr().err


POLICY = """
parties:
  master: {nodes: ['/master/*'], serve: ['/master/*']}
  operator: {nodes: ['/rejoin*'], call: [/aft/witness/request]}
  client2: {nodes: ['/client2*']}
"""


@pytest.fixture
def tls_tree(tmp_path):
    """A CA and the directories of parties master, operator and client2, and the policy above."""
    from aft_ftm import tls
    authority = str(tmp_path / 'authority')
    tls.make_authority(authority)
    for party in ('master', 'operator', 'client2'):
        tls.issue(authority, party)
        tls.export_party(authority, party, str(tmp_path / party))
    other = str(tmp_path / 'other_authority')   # another CA's certificate for master
    tls.make_authority(other)
    tls.issue(other, 'master')
    tls.export_party(other, 'master', str(tmp_path / 'forged_master'))
    (tmp_path / 'policy.yaml').write_text(POLICY)
    return tmp_path


def test_under_tls_a_launch_runs_as_the_site_s_party_never_as_the_caller_s(tls_tree):
    """Issue 16: rejoin --launch started the site with the caller's environment, so under TLS the site
    ran as the operator's party, whose nodes every peer refuses. The launched command now takes the
    party of --launch-tls-dir, which the policy must let run the site's nodes."""
    caller = {'AFT_TLS_DIR': str(tls_tree / 'operator'), 'AFT_TLS_PARTY': 'operator',
              'AFT_TLS_POLICY': str(tls_tree / 'policy.yaml'), 'OTHER': 'kept'}
    env = rejoin_command.launch_environment('master', 'roslaunch x y.launch', str(tls_tree / 'master'), caller)
    assert (env['AFT_TLS_DIR'], env['AFT_TLS_PARTY']) == (str(tls_tree / 'master'), 'master')
    assert env['AFT_TLS_POLICY'] == caller['AFT_TLS_POLICY'] and env['OTHER'] == 'kept'
    refusals = [
        (('master', 'roslaunch x', '', caller), 'would run as this command\'s party'),
        (('master', 'roslaunch x', str(tls_tree / 'client2'), caller), 'party client2 may not run a node named /master/'),
        (('master', 'roslaunch x', str(tls_tree), caller), 'no party'),       # the directories' parent
        (('master', 'roslaunch x', str(tls_tree / 'authority'), caller), 'holds the CA\'s private key'),
        (('master', 'roslaunch x', str(tls_tree / 'forged_master'), caller), 'not signed by this CA'),
        (('ma*', 'roslaunch x', str(tls_tree / 'master'), caller), 'a site name is'),
        (('master', 'roslaunch x', str(tls_tree / 'nowhere'), caller), 'cannot be read'),
        (('master', '', str(tls_tree / 'master'), caller), 'none is given'),
        (('master', 'roslaunch x', str(tls_tree / 'master'), {}), 'without TLS here'),
    ]
    for args, said in refusals:
        with pytest.raises(rejoin_command.ConfigError) as e:
            rejoin_command.launch_environment(*args)
        assert said in str(e.value), (args, str(e.value))
    # without TLS, and without a directory: the caller's environment, as before
    assert rejoin_command.launch_environment('master', 'x', '', {'A': '1'}) == {'A': '1'}


def test_a_refused_tls_launch_exits_2_having_started_and_asked_nothing(monkeypatch, tls_tree, capsys):
    monkeypatch.setenv('AFT_TLS_DIR', str(tls_tree / 'operator'))
    monkeypatch.setenv('AFT_TLS_PARTY', 'operator')
    monkeypatch.setenv('AFT_TLS_POLICY', str(tls_tree / 'policy.yaml'))
    asked, started = [], []
    monkeypatch.setattr(rejoin_command, 'status', lambda service: asked.append(service))
    monkeypatch.setattr(rejoin_command.subprocess, 'Popen', lambda *a, **k: started.append(a))
    assert rejoin_command.main(['master', '--launch', 'roslaunch x y.launch']) == 2
    assert asked == [] and started == [] and 'nothing started' in capsys.readouterr().err
