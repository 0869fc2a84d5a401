"""A server's own error reaches the client as the server worded it, without the replica's name."""
import pytest

from aft_ftm.service_errors import as_written, to_raise


@pytest.mark.parametrize('raised,written', [
    ("service [/master/account] responded with an error: b'service cannot process request: insufficient funds'",
     'service cannot process request: insufficient funds'),
    ('service [/slave/tr/account] responded with an error: b"error processing request: it\'s broken"',
     "error processing request: it's broken"),
    ("service [/master/account] responded with an error: b'caf\\xc3\\xa9'", 'caf\u00e9'),
    ('not executed: server /master/account unavailable (gone)', 'not executed: server /master/account unavailable (gone)'),
])
def test_proceed_keeps_what_the_server_wrote(raised, written):
    assert as_written(raised) == written
    assert '/master' not in as_written(raised) or raised.startswith('not executed')


def test_the_proxy_writes_it_again_the_same_way():
    assert to_raise('service cannot process request: insufficient funds') == ('service', 'insufficient funds')
    assert to_raise('error processing request: boom') == ('other', 'boom')
    assert to_raise('A&D: request assertion amount_within_limit failed') == \
        ('service', 'A&D: request assertion amount_within_limit failed')
