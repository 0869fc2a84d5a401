"""aft_ftm.where.site_tls: the TLS party of the nodes the Adaptation Engine starts for a site (no ROS
master). Issue 16: the engine launched a site's new nodes with its own environment, so under TLS they
spoke as the engine's party, which may not run a site's nodes, and every peer refused them. Taken
from a running node of the site, the party is checked against the engine's own policy and CA: that
node's process is whoever registered the name at the master (review of session 43)."""
import os

import pytest

from aft_ftm import tls, where

POLICY = """
parties:
  master: {nodes: ['/master/*'], serve: ['/master/*']}
  slave: {nodes: ['/slave/*'], serve: ['/slave/*']}
  engine: {nodes: ['/aft_adapt_*'], call: ['/master/*/rebind']}
  unbound: {serve: ['/x']}
"""
OPEN = "plaintext: ['*']\nparties: {master: {nodes: ['*']}, slave: {nodes: ['*']}}\n"


@pytest.fixture
def tree(tmp_path):
    """A CA, the directories of master, slave, engine and unbound, a policy; another CA's master."""
    authority = str(tmp_path / 'authority')
    tls.make_authority(authority)
    for party in ('master', 'slave', 'engine', 'unbound'):
        tls.issue(authority, party)
        tls.export_party(authority, party, str(tmp_path / party))
    other = str(tmp_path / 'other_authority')
    tls.make_authority(other)
    tls.issue(other, 'master')
    tls.export_party(other, 'master', str(tmp_path / 'forged_master'))
    (tmp_path / 'policy.yaml').write_text(POLICY)
    (tmp_path / 'open.yaml').write_text(OPEN)
    engine = {'AFT_TLS_DIR': str(tmp_path / 'engine'), 'AFT_TLS_PARTY': 'engine',
              'AFT_TLS_POLICY': str(tmp_path / 'policy.yaml')}
    return tmp_path, engine


def site(tmp_path, party, directory=None, policy='policy.yaml'):
    return {'AFT_TLS_DIR': str(tmp_path / (directory or party)), 'AFT_TLS_PARTY': party,
            'AFT_TLS_POLICY': str(tmp_path / policy)}


def test_the_new_nodes_take_the_party_of_their_site_with_the_engine_s_own_policy(tree):
    tmp_path, engine = tree
    got = where.site_tls(site(tmp_path, 'master', policy='open.yaml'), '/', ['/master/tr/protocol'], engine)
    # a policy of the other process's choosing is never taken (one that opens everything, here)
    assert got == {'AFT_TLS_DIR': str(tmp_path / 'master'), 'AFT_TLS_PARTY': 'master',
                   'AFT_TLS_POLICY': str(tmp_path / 'policy.yaml')}
    assert where.with_tls({'KEEP': '1', 'AFT_TLS_PARTY': 'engine'}, got)['AFT_TLS_PARTY'] == 'master'
    # a directory relative to that process's working directory, resolved
    relative = dict(site(tmp_path, 'master'), AFT_TLS_DIR='master')
    assert where.site_tls(relative, str(tmp_path), ['/master/x'], engine)['AFT_TLS_DIR'] == str(tmp_path / 'master')


@pytest.mark.parametrize('case,words', [
    ('no tls', 'runs without TLS'),
    ('another site', 'party slave may not run a node named /master/tr/protocol'),
    # ... whatever policy that process names (one that binds every name to any party, here)
    ('another site, its own policy open', 'party slave may not run a node named /master/tr/protocol'),
    ('unbound party', 'bound to no node names'),
    ('another CA', 'not signed by this CA'),
    ('another party\'s certificate', "names ['slave'], not party master"),
    ('no directory', 'cannot be read'),
])
def test_a_party_that_cannot_run_the_nodes_is_refused_naming_why(tree, case, words):
    """Each started so would be refused by every peer, or would speak as a party it is not: a process
    registered at the master under a site's name (anyone's) with an environment of its choosing."""
    import shutil
    tmp_path, engine = tree
    their = {
        'no tls': {},
        'another site': site(tmp_path, 'slave'),
        'another site, its own policy open': site(tmp_path, 'slave', policy='open.yaml'),
        'unbound party': site(tmp_path, 'unbound'),
        'another CA': site(tmp_path, 'master', 'forged_master'),
        'no directory': site(tmp_path, 'master', 'nowhere'),
    }.get(case)
    if case == 'another party\'s certificate':   # slave's pair under master's names
        os.makedirs(str(tmp_path / 'swapped'))
        for mine, theirs in zip(tls.certificate_files(str(tmp_path / 'swapped'), 'master'),
                                tls.certificate_files(str(tmp_path / 'slave'), 'slave')):
            shutil.copyfile(theirs, mine)
        their = site(tmp_path, 'master', 'swapped')
    with pytest.raises(where.WhereError) as e:
        where.site_tls(their, '/', ['/master/tr/protocol'], engine)
    assert words in str(e.value), str(e.value)


def test_the_engine_s_policy_is_given_as_an_absolute_path(tree, monkeypatch):
    """The new nodes run in roslaunch's working directory (ROS_HOME), not the engine's: a policy named
    relative to the engine's would pass its dry run and stop every new node (review of session 43)."""
    tmp_path, engine = tree
    monkeypatch.chdir(str(tmp_path))
    got = where.site_tls(site(tmp_path, 'master'), '/', ['/master/x'], dict(engine, AFT_TLS_POLICY='policy.yaml'))
    assert got['AFT_TLS_POLICY'] == str(tmp_path / 'policy.yaml')
    with pytest.raises(where.WhereError) as e:
        where.site_tls(site(tmp_path, 'master'), '/', ['/master/x'], {'AFT_TLS_DIR': engine['AFT_TLS_DIR']})
    assert 'AFT_TLS_POLICY' in str(e.value)


def test_without_tls_here_nothing_is_taken(tree):
    tmp_path, _ = tree
    assert where.site_tls(site(tmp_path, 'master'), '/', ['/master/x'], {'KEEP': '1'}) is None
    assert where.with_tls({'KEEP': '1'}, None) == {'KEEP': '1'}


def test_a_process_that_cannot_be_read_is_an_error_naming_it():
    import subprocess
    import sys
    proc = subprocess.Popen([sys.executable, '-c', 'pass'])
    proc.wait()
    with pytest.raises(where.WhereError) as e:
        where.process_setting(proc.pid)
    assert str(proc.pid) in str(e.value)


def test_the_engine_refuses_a_launch_it_cannot_give_one_checked_party_before_anything_changes(tree, monkeypatch):
    """Engine._launch_tls, in the dry run: each new node's party from the running node it was placed
    by; a node placed by none, or one launch whose nodes join sites of two parties (one roslaunch,
    one environment), is a ScriptError (the script refused, nothing changed)."""
    from aft_ftm.adaptation import ScriptError
    from aft_ftm.ros import adaptation_engine
    tmp_path, engine = tree
    for name, value in engine.items():
        monkeypatch.setenv(name, value)
    processes = {10: (site(tmp_path, 'master'), '/'), 20: (site(tmp_path, 'slave'), '/')}
    monkeypatch.setattr(adaptation_engine, 'process_setting', lambda pid: processes[pid])
    plan = adaptation_engine.Engine._launch_tls
    got = plan(['/master/tr/protocol', '/master/tr/after'], {'/master/tr/protocol': 10, '/master/tr/after': 10})
    assert got['AFT_TLS_PARTY'] == 'master' and got['AFT_TLS_POLICY'] == engine['AFT_TLS_POLICY']
    for names, neighbours, words in (
            (['/master/tr/protocol'], {}, 'joins no site found'),
            (['/master/x', '/slave/x'], {'/master/x': 10, '/slave/x': 20}, 'different TLS parties'),
            (['/master/x'], {'/master/x': 20}, 'party slave may not run a node named /master/x')):
        with pytest.raises(ScriptError) as e:
            plan(names, neighbours)
        assert words in str(e.value), str(e.value)
    for name in engine:   # without TLS here: nothing asked, nothing given
        monkeypatch.delenv(name)
    assert plan(['/master/x'], {}) is None
