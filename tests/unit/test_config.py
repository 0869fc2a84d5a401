"""The typed parameter converters: each refuses what it does not mean, naming the parameter."""
import pytest

from aft_ftm import config
from aft_ftm.errors import ConfigError


@pytest.mark.parametrize('value,expected', [(True, True), (False, False), ('true', True), ('False', False),
                                            (' TRUE ', True)])
def test_flag_accepts_true_and_false_only(value, expected):
    assert config.flag('~x', value) is expected


@pytest.mark.parametrize('value', ['no', 'yes', '1', '0', 1, 0, '', None, 'flase'])
def test_flag_refuses_anything_else_naming_the_parameter(value):
    # bool('false') is True: a safety declaration such as LFR's server_deterministic must never be read that way
    with pytest.raises(ConfigError, match='~server_deterministic must be true or false'):
        config.flag('~server_deterministic', value)


def test_numbers_with_ranges():
    assert config.number_in(0.0, 1.0)('~p', 0.25) == 0.25
    assert config.number_in(0.0, 1.0)('~p', '1') == 1.0
    for bad in (1.5, -0.1, 'x', None, True, float('nan')):
        with pytest.raises(ConfigError, match='~p must be a number'):
            config.number_in(0.0, 1.0)('~p', bad)
    assert config.non_negative_float('~t', 0) == 0.0 and config.non_negative_float('~t', 0.5) == 0.5
    with pytest.raises(ConfigError, match='~t must be > 0'):
        config.non_negative_float('~t', -1)
    assert config.number('~m', -3) == -3.0
    with pytest.raises(ConfigError, match='finite'):
        config.number('~m', float('inf'))


def test_named_lists():
    assert config.name_list('~l', []) == [] and config.name_list('~l', ['a', ' b ']) == ['a', 'b']
    for bad in ('after', None, ['a', ''], ['a', 3]):
        with pytest.raises(ConfigError, match=r'~l'):
            config.name_list('~l', bad)
    assert config.some_names('~l', ['after']) == ['after']
    with pytest.raises(ConfigError, match='at least one'):
        config.some_names('~l', [])


def test_choices_and_optional_names():
    role = config.choice('primary', 'backup')
    assert role('~role', 'backup') == 'backup'
    with pytest.raises(ConfigError, match='~role must be one of backup, primary'):
        role('~role', 'leader')
    assert config.optional_name('~w', '') == '' and config.optional_name('~w', ' /w ') == '/w'
    with pytest.raises(ConfigError):
        config.optional_name('~w', '   ')


def test_number_map():
    assert config.number_map('~watch', {'imu': 1}) == {'imu': 1.0}
    for bad in ([1], {'imu': 0}, {'imu': 'x'}):
        with pytest.raises(ConfigError, match='~watch'):
            config.number_map('~watch', bad)


def test_a_witness_is_none_or_a_service_a_witness_offers():
    assert config.witness_service('~witness', '') == '' and config.witness_service('~witness', 'none') == ''
    assert config.witness_service('~witness', ' /nav/witness/request ') == '/nav/witness/request'
    assert config.witness_service('~witness', '/request') == '/request'
    assert config.witness_service('~witness', '/nav/_w2/9/witness/request') == '/nav/_w2/9/witness/request'
    # its configurations are published beside ~request: any other name would follow a topic nobody publishes.
    # "None" and " none " are a witness to the launch files (their test is exact) and were none to the
    # nodes: the primary's Protocol waited as a backup for ever (review of session 40). A relative name
    # resolved in each node's own namespace, to as many topics.
    for bad in ('/nav/witness', '/nav/witness/configuration', 'true', 3, None, '   ', 'None', ' none ', 'NONE',
                'witness/request', 'request', '/nav/witnes s/request', '/nav//witness/request', '/1nav/request'):
        with pytest.raises(ConfigError, match='~witness'):
            config.witness_service('~witness', bad)
