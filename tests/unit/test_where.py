"""aft_ftm.where.run_where: a node started for a site takes that site's TLS party (no ROS master)."""
import os
import subprocess
import sys

import psutil
import pytest

from aft_ftm import where
from aft_ftm.sites import wait_until

TLS = {'AFT_TLS_DIR': '/tls/master', 'AFT_TLS_PARTY': 'master', 'AFT_TLS_POLICY': '/tls/policy.yaml'}
ENGINE = {'AFT_TLS_DIR': '/tls/engine', 'AFT_TLS_PARTY': 'engine', 'AFT_TLS_POLICY': '/tls/policy.yaml', 'KEEP': '1'}


@pytest.fixture
def site_process():
    """A process standing for a site's launcher, started with the given environment."""
    started = []

    def start(env):
        proc = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'], env=dict(env, PATH=os.environ['PATH']))
        started.append(proc)
        # Popen returns before the kernel shows the new program's environment (aft_ftm.trust.command_line)
        assert wait_until(lambda: psutil.Process(proc.pid).environ().get('PATH'), 5.0, 0.005)
        return proc
    yield start
    for proc in started:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_the_nodes_of_a_tls_site_take_its_party_not_the_engine_s(site_process):
    """Issue 16: the engine launched a site's new nodes with its own environment, so under TLS they
    spoke as the engine's party, which may not run a site's nodes: every peer refused them."""
    argv, env = where.run_where(site_process(TLS).pid, ['roslaunch', 'x'], ENGINE)
    assert argv == ['roslaunch', 'x']   # the same network namespace: started here
    assert {k: env[k] for k in TLS} == TLS and env['KEEP'] == '1'


def test_a_site_without_tls_gets_nodes_without_tls(site_process):
    """The site's setting, whichever it is: its nodes in clear are not given the engine's certificate."""
    _, env = where.run_where(site_process({}).pid, ['x'], ENGINE)
    assert not any(k in env for k in TLS) and env['KEEP'] == '1'


def test_an_unreadable_site_under_tls_is_an_error_not_the_engine_s_party(site_process):
    proc = site_process({})
    proc.kill()
    proc.wait()
    pid = proc.pid
    with pytest.raises(where.WhereError) as e:
        where.run_where(pid, ['x'], ENGINE)
    assert 'TLS party is unknown' in str(e.value) and str(pid) in str(e.value)
    # without TLS nothing is at stake: argv and env as given
    assert where.run_where(pid, ['x'], {'KEEP': '1'}) == (['x'], {'KEEP': '1'})

