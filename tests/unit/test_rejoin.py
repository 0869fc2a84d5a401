"""Registering again with a restarted ROS master (aft_ftm.rejoin, aft_ftm.ros.rejoin's period). No ROS master."""
import pytest

from aft_ftm.errors import ConfigError
from aft_ftm.rejoin import Lookup, Rejoin, judge, master_pid, misdirected_shutdown

URI = 'http://10.0.0.2:4101/'


def test_the_lookup_of_the_nodes_own_name_says_whether_to_register_again():
    assert judge((1, 'node api', 'http://10.0.0.2:4101'), URI) == Lookup.KNOWN   # a trailing slash aside
    assert judge((-1, 'unknown node [/witness]', ''), URI) == Lookup.UNKNOWN
    assert judge((1, 'node api', 'http://10.0.0.3:4101/'), URI) == Lookup.REPLACED
    assert judge(None, URI) == Lookup.UNREACHABLE


SRV = 'rosrpc://10.0.0.2:4102'
NODE = (1, 'node api', URI)


@pytest.mark.parametrize('service,expected', [
    ((1, 'rosrpc URI', SRV), Lookup.KNOWN),
    ((-1, 'no provider', ''), Lookup.UNKNOWN),                        # removed by a clean-up: register again
    ((1, 'rosrpc URI', 'rosrpc://10.0.0.9:4102'), Lookup.UNKNOWN),    # another's: ours are gone
    (None, Lookup.UNREACHABLE),
])
def test_a_node_known_by_name_whose_registrations_a_clean_up_removed_registers_again(service, expected):
    """rosnode cleanup takes a live node that answers its ping late for dead and unregisters everything
    of it; the master may still know its name. The node's own ~get_loggers service tells."""
    assert judge(NODE, URI, service, SRV) == expected
    assert judge((1, 'node api', 'http://10.0.0.3:4101/'), URI, service, SRV) == Lookup.REPLACED
    assert judge(NODE, URI) == Lookup.KNOWN   # no service known to the node yet: by name alone


def test_a_new_master_is_registered_with_again_even_where_it_knows_the_node_by_newer_topics():
    rejoin = Rejoin()
    K, U, N = Lookup.KNOWN, Lookup.UNKNOWN, Lookup.UNREACHABLE
    assert rejoin.step(100, K) == (False, None) and rejoin.pid == 100
    again, said = rejoin.step(None, N)   # the master killed
    assert not again and 'does not answer' in said
    assert rejoin.step(None, N) == (False, None)   # said once
    again, said = rejoin.step(200, K)   # a new master: known only by a subscription made since
    assert again and 'registering again' in said
    again, _ = rejoin.step(200, K)      # not registered yet (the attempt failed): asks again
    assert again
    rejoin.registered(200)
    assert rejoin.step(200, K) == (False, None) and rejoin.rejoins == 1
    assert rejoin.step(200, U)[0]       # the same pid (pid 1 of a container) but the node unknown
    rejoin.registered(200)
    again, said = rejoin.step(300, Lookup.REPLACED)
    assert not again and 'another node has taken this name' in said
    assert rejoin.step(300, Lookup.REPLACED) == (False, None)   # said once


def test_the_master_pid_is_read_from_its_answer():
    assert master_pid((1, '', 4242)) == 4242
    assert master_pid((-1, 'error', 0)) is None and master_pid(None) is None


def test_the_period_comes_from_the_environment_and_a_bad_one_is_named():
    from aft_ftm.ros.rejoin import DEFAULT_PERIOD, period_from_env
    assert period_from_env({}) == DEFAULT_PERIOD
    assert period_from_env({'AFT_MASTER_REJOIN_PERIOD': '0'}) == 0.0
    assert period_from_env({'AFT_MASTER_REJOIN_PERIOD': '0.25'}) == 0.25
    for bad in ('soon', '-1', 'nan'):
        with pytest.raises(ConfigError, match='AFT_MASTER_REJOIN_PERIOD'):
            period_from_env({'AFT_MASTER_REJOIN_PERIOD': bad})


@pytest.mark.parametrize('message, own, expected', [
    ('[/slave/crash_detector] Reason: new node registered with same name', '/slave/proceed', True),
    ('[/slave/proceed] Reason: new node registered with same name', '/slave/proceed', False),   # meant for it
    ('', '/slave/proceed', False),                                   # rosnode kill: obeyed
    ('user request', '/slave/proceed', False),
    ('[/slave/crash_detector] Reason: something else', '/slave/proceed', False),
    # fencing's request to a name registered at another node's address (a forged alias) is not for it
    ('[/master/forged] Reason: fail-silence of /master', '/slave/protocol', True),
    ('[/master/after] Reason: fail-silence of /master', '/master/after', False),
])
def test_a_masters_shutdown_naming_another_node_is_misdirected(message, own, expected):
    """A host back with its old address: the master's shutdown of a dead node's old address reaches
    the new process that now has that port (found on emulated hosts: a relaunched site's Proceed shut
    down for its crash detector). Only a request naming another node is ignored."""
    assert misdirected_shutdown(message, own) is expected
