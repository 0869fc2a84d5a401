"""The campaign's table, replay command and error classification. No ROS."""
import pytest

from aft_examples.campaign_report import format_table, replay_command, table
from aft_examples.history import classify_error


@pytest.mark.parametrize('text,outcome', [
    ('service [/account1] unavailable', 'not_executed'),
    ('unable to connect to service: [Errno 111] Connection refused', 'not_executed'),
    # seen on emulated hosts (seed 11), a Proxy killed 17 ms before: the header exchange was reset
    ('unable to connect to service: [Errno 104] Connection reset by peer', 'not_executed'),
    ('service cannot process request: not executed: the reply cache is full', 'not_executed'),
    ('unable to contact master', 'not_executed'),   # the ROS master killed: the lookup, before anything is sent
    ('transport error completing service call: unable to receive data from sender, check sender\'s logs for '
     'details', 'indeterminate'),
    ('outcome UNKNOWN: no reply to request 17 within 30.0 s', 'indeterminate'),
    ('service cannot process request: cannot withdraw 9 from a balance of 3', 'error'),
    ("service [/account1] responded with an error: b'service cannot process request: cannot withdraw 18 from a "
     "balance of 12'", 'error'),
    ("service [/account1] responded with an error: b'not executed: the reply cache is full'", 'not_executed'),
    ("service [/account2] responded with an error: b'service cannot process request: outcome UNKNOWN: no reply to "
     "request 5 within 30.0 s'", 'indeterminate'),
])
def test_a_failed_call_is_classified_by_what_its_client_can_know(text, outcome):
    assert classify_error(text) == outcome


def test_table_by_kind_with_a_total_row():
    records = [dict(kind='kill', outcome='failover', unavailable=0.1, unavailable_fault=0.04,
                    unavailable_repair=0.1),
               dict(kind='kill', outcome='restarted', unavailable=0.3),
               dict(kind='freeze_node', outcome='absorbed', unavailable=0.0),
               dict(kind='power_loss', outcome='unhealed: the witness does not answer', unavailable=2.0)]
    rows = table(records)
    assert [r[0] for r in rows] == ['freeze_node', 'kill', 'power_loss', 'all']
    kill = rows[1]
    assert kill[1] == 2 and kill[2] == '1 failover, 1 restarted' and kill[3] == pytest.approx(100)
    assert kill[5] == pytest.approx(300)
    # The fault's share (a record without a repair: all of it) and the repair's, by nearest rank.
    assert kill[6] == pytest.approx(40) and kill[7] == pytest.approx(0)
    assert rows[0][6:] == (0, 0)
    assert rows[2][2] == '1 unhealed' and rows[-1][1] == 4
    text = format_table(rows)
    assert text.splitlines()[0].startswith('| fault kind') and '| all ' in text


def test_replay_command_names_the_segment():
    assert replay_command(50, 7, 1, 25, 2) == 'scripts/campaign --faults 50 --seed 7 --per-segment 25 --clients 2 ' \
                                              '--segment 1'
