"""Decision logic of TR, A&D and the fault injector, and the Table I data, table-driven. No ROS."""
import types

import pytest

from aft_ftm import assertions, mechanisms
from aft_ftm.corruption import Corruptor, flip_bit, numeric_fields
from aft_ftm.errors import ConfigError
from aft_ftm.voting import Outcome, TimeRedundancyVote

OK, BAD, BAD2 = 'right', 'flipped', 'offset'


# -- Time Redundancy: mechanism x injected fault -> outcome -----------------------------------------
@pytest.mark.parametrize('executions,results,outcome,value,masked', [
    (3, [OK, OK], Outcome.DECIDED, OK, 0),                   # no fault: two executions agree
    (3, [BAD, OK, OK], Outcome.DECIDED, OK, 1),              # transient fault in the 1st execution: masked
    (3, [OK, BAD, OK], Outcome.DECIDED, OK, 1),              # ... in the 2nd: masked
    (3, [BAD, BAD2, OK], Outcome.NO_MAJORITY, None, 0),      # two faults (outside the model): detected
    (3, [BAD, BAD], Outcome.DECIDED, BAD, 0),                # the same wrong value twice (permanent or
                                                             # common-mode fault, outside the model): passes
    (2, [OK, BAD], Outcome.NO_MAJORITY, None, 0),            # duplex: detects, cannot decide
    (5, [BAD, OK, BAD2, OK, OK], Outcome.DECIDED, OK, 2),
])
def test_time_redundancy_vote(executions, results, outcome, value, masked):
    vote = TimeRedundancyVote(executions)
    verdicts = [vote.add('req', r) for r in results]
    assert all(v.outcome == Outcome.REPEAT for v in verdicts[:-1])
    final = verdicts[-1]
    assert (final.outcome, final.value, final.masked) == (outcome, value, masked)
    assert final.value in (None, results[-1])     # the decided value is the last execution's
    assert vote.pending() == 0


@pytest.mark.parametrize('executions', [1, 0, -3, 2.5, True])
def test_time_redundancy_needs_at_least_two_executions(executions):
    with pytest.raises(ConfigError, match='at least 2 executions'):
        TimeRedundancyVote(executions)


def test_votes_of_two_requests_do_not_mix():
    vote = TimeRedundancyVote(3)
    assert vote.add('a', OK).outcome == Outcome.REPEAT
    assert vote.add('b', BAD).outcome == Outcome.REPEAT
    assert vote.add('a', OK).outcome == Outcome.DECIDED


def test_one_execution_heard_twice_is_counted_once():
    """Review of session 34: one corrupted execution delivered twice made a majority of 3 on its own."""
    vote = TimeRedundancyVote(3)
    assert vote.add('a', BAD, 0).outcome == Outcome.REPEAT
    assert vote.add('a', BAD, 0) is None                      # the same execution again: not a vote
    assert vote.add('a', OK, 1).outcome == Outcome.REPEAT
    final = vote.add('a', OK, 2)
    assert (final.outcome, final.value, final.masked) == (Outcome.DECIDED, OK, 1)


# -- Assertion & Duplex -------------------------------------------------------------------------------
def passes(*_):
    return True


def silent(*_):
    return None


def fails(*_):
    return False


def explains(*_):
    return 'speed 12 km/h is above 10 km/h with the steering lock engaged'


def asserts(*_):
    assert 1 == 2, 'one is not two'


def crashes(*_):
    raise KeyError('speed')


class NumpyLikeFalse(object):
    """What numpy.all() returns for a failed check: numpy.False_, false but not ``False``."""
    def __bool__(self):
        return False

    def __repr__(self):
        return 'np.False_'


class Ambiguous(object):
    """A numpy array returned by mistake: its truth cannot be told."""
    def __bool__(self):
        raise ValueError('the truth value of an array with more than one element is ambiguous')


def numpy_false(*_):
    return NumpyLikeFalse()


def zero(*_):
    return 0


def an_array(*_):
    return Ambiguous()


def not_a_number(*_):
    return float('nan')


def a_huge_int(*_):
    return 10 ** 400


def numpy_nan(*_):
    import numpy
    return numpy.array(numpy.nan)     # a 0-d array: not a float, and bool() of it is True


def decimal_nan(*_):
    import decimal
    return decimal.Decimal('NaN')


def decimal_snan(*_):
    import decimal
    return decimal.Decimal('sNaN')


def complex_nan(*_):
    return complex('nan')


@pytest.mark.parametrize('fn,detail', [
    (passes, None), (silent, None), (fails, 'returned False'),
    (explains, 'speed 12 km/h is above 10 km/h'), (asserts, 'one is not two'),
    (crashes, "raised KeyError: 'speed'"),                   # cannot be evaluated: violated, never passed
    # Review, stop 39: only ``is False`` was a violation; numpy.all()'s False_ let the reply through.
    (numpy_false, 'returned np.False_'), (zero, 'returned 0'), (an_array, 'not a verdict: the truth value'),
    # Review of session 34: bool(nan) is True, so a verdict computed from a NaN field passed.
    (not_a_number, 'returned nan, not a verdict'), (a_huge_int, None),
    # Review of session 36: NaN-like values that are not floats passed.
    (numpy_nan, 'returned nan, not a verdict'), (decimal_nan, 'returned nan, not a verdict'),
    (decimal_snan, 'returned nan, not a verdict'), (complex_nan, 'returned nan, not a verdict'),
])
def test_assertion_outcomes(fn, detail):
    violations = assertions.check([(fn.__name__, fn)], 'request', 'response')
    if detail is None:
        assert violations == []
    else:
        assert len(violations) == 1 and violations[0][0] == fn.__name__ and detail in violations[0][1]


@pytest.mark.parametrize('spec,error', [
    ('aft_examples.bank:balance_never_negative', None),
    ('aft_examples.bank', 'must be named as package.module:function'),
    ('aft_ftm.nope:f', 'cannot import aft_ftm.nope'),
    ('aft_examples.bank:missing', 'module aft_examples.bank has no missing'),
    ('aft_examples.bank:LIMIT', 'LIMIT is not callable'),
    (42, 'must be named'),
])
def test_assertions_are_loaded_at_start_with_a_clear_error(spec, error):
    if error is None:
        name, fn = assertions.load(spec)
        assert name == spec and callable(fn)
    else:
        with pytest.raises(ConfigError, match=error):
            assertions.load(spec)


def test_assertion_list_parameter_must_be_a_list():
    with pytest.raises(ConfigError, match='~reply_assertions must be a list'):
        assertions.load_all('aft_examples.bank:balance_never_negative', '~reply_assertions')


def test_bank_safety_assertions():
    from aft_examples.bank import amount_within_limit, balance_never_negative
    assert amount_within_limit(types.SimpleNamespace(amount=10)) is True
    assert 'over the limit' in amount_within_limit(types.SimpleNamespace(amount=5000))
    assert 'negative' in balance_never_negative(None, types.SimpleNamespace(balance=-1))


# -- fault injection ----------------------------------------------------------------------------------
class Pose(object):
    __slots__ = ('x', 'y')
    _slot_types = ('float64', 'float64')

    def __init__(self, x=0.0, y=0.0):
        self.x, self.y = x, y


class Response(object):
    __slots__ = ('balance', 'count', 'digest', 'pose')
    _slot_types = ('int64', 'uint64', 'string', 'demo/Pose')

    def __init__(self, balance=10, count=3, digest='abc', pose=None):
        self.balance, self.count, self.digest, self.pose = balance, count, digest, pose or Pose(1.0, 2.0)


def test_numeric_fields_include_nested_messages_not_strings():
    assert [('.'.join(p), t) for p, t in numeric_fields(Response())] == [
        ('balance', 'int64'), ('count', 'uint64'), ('pose.x', 'float64'), ('pose.y', 'float64')]


@pytest.mark.parametrize('value,slot_type,bit,expected', [
    (0, 'int64', 3, 8), (8, 'int64', 3, 0), (0, 'int8', 7, -128), (5, 'uint8', 1, 7),
    (1.0, 'float64', 63, -1.0),
])
def test_flip_bit(value, slot_type, bit, expected):
    assert flip_bit(value, slot_type, bit) == expected


@pytest.mark.parametrize('mode,field,check', [
    ('offset', 'balance', lambda r: r.balance == 10 - 7),
    ('offset', 'pose.x', lambda r: r.pose.x == 1.0 - 7),
    ('offset', 'count', lambda r: r.count == 3 + 7),          # never below zero for an unsigned field
    ('bitflip', 'balance', lambda r: r.balance != 10 and bin(r.balance ^ 10).count('1') == 1),
])
def test_armed_corruption_hits_the_named_field_once(mode, field, check):
    injector = Corruptor(mode, probability=0.0, magnitude=-7, seed=1)
    injector.arm(1, mode, -7, field)
    original = Response()
    corrupted = injector.relay(original)
    assert check(corrupted) and original.balance == 10 and original.pose.x == 1.0   # the original is intact
    assert injector.relay(Response()).balance == 10                                  # only once
    assert injector.injected == 1


def test_stuck_value_repeats_the_previous_result():
    injector = Corruptor('stuck', seed=1)
    injector.relay(Response(balance=1))
    injector.arm(2)
    assert injector.relay(Response(balance=2)).balance == 1
    assert injector.relay(Response(balance=3)).balance == 2   # stuck at the last real value


def test_probability_corrupts_about_that_share():
    injector = Corruptor('offset', probability=0.25, magnitude=5, seed=7)
    changed = sum(1 for _ in range(4000) if injector.relay(Response()).balance != 10)
    assert abs(injector.injected / 4000.0 - 0.25) < 0.03
    assert 0 < changed <= injector.injected     # an offset lands on one of four numeric fields


@pytest.mark.parametrize('kwargs,error', [
    (dict(mode='melt'), 'fault mode must be one of'), (dict(probability=1.5), 'within \\[0, 1\\]')])
def test_bad_injector_configuration_is_refused(kwargs, error):
    with pytest.raises(ConfigError, match=error):
        Corruptor(**kwargs)


def test_unknown_field_is_named():
    injector = Corruptor('offset')
    injector.arm(1, field='speed')
    with pytest.raises(ConfigError, match="no numeric field 'speed' \\(it has: balance, count, pose.x, pose.y\\)"):
        injector.relay(Response())


# -- Table I ------------------------------------------------------------------------------------------
@pytest.mark.parametrize('name,bandwidth,cpus,deterministic,state_access', [
    ('pbr', 'high', 2, False, True), ('lfr', 'low', 2, True, False), ('tr', 'nil', 1, True, True)])
def test_table_one_as_in_the_paper(name, bandwidth, cpus, deterministic, state_access):
    m = mechanisms.mechanism(name)
    assert (m.bandwidth, m.cpus, m.deterministic, m.state_access) == (bandwidth, cpus, deterministic, state_access)


def test_a_composition_tolerates_the_union_of_its_parts_fault_models():
    c = mechanisms.compose(['sec', 'pbr', 'tr'])
    assert c.faults == {mechanisms.CRASH, mechanisms.TRANSIENT_VALUE, mechanisms.EAVESDROPPING,
                        mechanisms.TAMPERING}
    assert (c.name, c.cpus, c.bandwidth, c.deterministic, c.state_access) == ('sec+pbr+tr', 2, 'high', True, True)


def test_unknown_mechanism_is_named():
    with pytest.raises(ConfigError, match="unknown mechanism 'nvp' \\(known: pbr, lfr, tr, ad, sec\\)"):
        mechanisms.compose(['pbr', 'nvp'])


def test_a_reply_whose_request_never_reaches_ad_after_is_handed_back_after_its_wait_never_kept_for_ever():
    """Review of session 34: A&D's After kept a reply whose request it never saw (it started again after
    Before passed the request on) for ever; only the Protocol's timeout told anything. Now it waits
    its request ``wait`` seconds, in either order of arrival, then is handed back for an alarm;
    requests waiting for their replies are bounded, the oldest handed back."""
    from aft_ftm.assertions import Pairing
    pairing = Pairing(wait=2.0, max_requests=3)
    assert pairing.reply('a', 'reply a', now=10.0) is None          # before its request: waits
    assert pairing.request('a', 'request a') == ('reply a', None)   # its request came: checked now
    assert pairing.request('b', 'request b') == (None, None)
    assert pairing.reply('b', 'reply b', now=11.0) == 'request b'
    assert pairing.reply('lost', 'reply lost', now=11.0) is None
    assert pairing.expired(12.9) == []                               # still within its wait
    assert pairing.expired(13.0) == ['reply lost'] and pairing.expired(99.0) == []
    assert pairing.request('lost', 'request lost (too late)') == (None, None)   # kept now, its reply gone
    for k in 'cd':
        assert pairing.request(k, 'request ' + k) == (None, None)
    assert pairing.request('e', 'request e') == (None, 'request lost (too late)')   # the oldest goes
    assert sorted(pairing.requests) == ['c', 'd', 'e'] and pairing.replies == {}
