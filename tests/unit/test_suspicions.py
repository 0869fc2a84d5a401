"""The campaign's judgement of the crash detectors' verdicts: explained by a fault of the site they
name, or false suspicions. No ROS."""
import random

from aft_examples.suspicions import (Verdict, format_summary, heard_again_of, judge, logged_verdicts, merge, rejoin_of,
                                    sites_touched, summary)


def record(index, start, healed_at, sites, kind='kill', outcome='failover', unavailable=0.04):
    return dict(index=index, start=start, end=start + 0.01, healed_at=healed_at, sites=sorted(sites), kind=kind,
                outcome=outcome, unavailable=unavailable)


def test_a_fault_touches_the_sites_its_roles_name_when_it_came():
    assert sites_touched('primary/after', 'slave', 'master') == {'slave'}
    assert sites_touched('backup', 'slave', 'master') == {'master'}
    assert sites_touched('primary-backup', 'master', 'slave') == {'master', 'slave'}
    assert sites_touched('client-backup', 'master', 'slave') == {'slave'}
    for target in ('proxy', 'witness', 'ros_master', 'switch', 'client-witness'):
        assert sites_touched(target, 'master', 'slave') == set()
    # A pair not whole: the missing role touches nothing.
    assert sites_touched('backup/proceed', 'master', '') == set()


def test_a_verdict_about_the_faulty_site_inside_its_window_is_explained_and_timed():
    records = [record(0, 100.0, 101.0, {'master'})]
    explained, false, detections = judge([Verdict(100.035, 'slave', 'master', 'silent')], records)
    assert len(explained) == 1 and not false
    assert abs(detections[0] - 0.035) < 1e-9


def test_verdicts_outside_every_window_or_about_another_site_are_false_suspicions():
    records = [record(0, 100.0, 101.0, {'master'}), record(1, 105.0, 106.0, set(), kind='freeze_node')]
    verdicts = [Verdict(99.0, 'slave', 'master', 'before any fault'),          # while starting
                Verdict(100.5, 'master', 'slave', 'the other site'),           # during a fault of master
                Verdict(101.2, 'slave', 'master', 'after the healing'),
                Verdict(105.5, 'slave', 'master', 'a fault of the witness')]   # nothing of a replica touched
    explained, false, detections = judge(verdicts, records)
    assert not explained and not detections
    assert [v.reason for v in false] == ['before any fault', 'the other site', 'after the healing',
                                         'a fault of the witness']


def test_only_the_first_verdict_times_a_fault_and_a_pair_fault_is_not_timed():
    records = [record(0, 10.0, 12.0, {'master'}), record(1, 20.0, 22.0, {'master', 'slave'}, kind='partition_pair')]
    verdicts = [Verdict(10.2, 'slave', 'master', ''), Verdict(10.05, 'slave', 'master', ''),
                Verdict(20.03, 'master', 'slave', ''), Verdict(20.04, 'slave', 'master', '')]
    explained, false, detections = judge(verdicts, records)
    assert len(explained) == 4 and not false
    assert set(detections) == {0} and abs(detections[0] - 0.05) < 1e-9


def test_the_summary_counts_every_verdict_once_whatever_their_order():
    rng = random.Random(7)
    records = [record(i, 10.0 * i, 10.0 * i + rng.uniform(0.5, 3.0), {rng.choice(['master', 'slave'])})
               for i in range(30)]
    verdicts = [Verdict(rng.uniform(0, 300), rng.choice(['master', 'slave']), rng.choice(['master', 'slave']), '')
                for _ in range(200)]
    forward = summary(verdicts, records)
    shuffled = list(verdicts)
    rng.shuffle(shuffled)
    assert summary(shuffled, records) == forward
    assert forward['explained'] + forward['false_suspicions'] == forward['verdicts'] == 200
    lines = format_summary(forward, 0.03)
    assert lines[0].startswith('detection (crash detector timeout 30 ms): 200 verdicts')
    assert len(lines) == 1 + forward['false_suspicions']


def test_a_campaign_without_verdicts_says_so():
    s = summary([], [record(0, 1.0, 2.0, {'master'}, outcome='absorbed')])
    assert s['false_suspicions'] == 0 and s['detection_ms_median'] is None and s['failovers'] == 0
    assert 'none detected' in format_summary(s, 0.03)[0]


def test_a_failover_is_timed_until_the_relaunch_and_its_rejoin_apart():
    # Two failovers: 40 and 60 ms before the relaunch, 150 and 90 ms during the re-join; a restart
    # (not a failover) and a record from before the split (no shares: the whole window is the fault's).
    records = [dict(record(0, 1.0, 9.0, {'master'}, unavailable=0.15), unavailable_fault=0.04, unavailable_repair=0.15),
               dict(record(1, 11.0, 19.0, {'slave'}, unavailable=0.09), unavailable_fault=0.06, unavailable_repair=0.09),
               record(2, 21.0, 29.0, {'slave'}, outcome='restarted', unavailable=2.0),
               record(3, 31.0, 39.0, {'master'}, unavailable=0.05)]
    s = summary([], records)
    assert s['failovers'] == 3
    assert abs(s['failover_unavailable_ms_median'] - 50.0) < 1e-9   # 40, 50, 60
    assert abs(s['failover_rejoin_ms_median'] - 90.0) < 1e-9       # 0, 90, 150
    assert 'until the failed site is relaunched, then 90.0 ms during its re-join' in format_summary(s, 0.03)[0]


def test_a_site_declared_failed_again_after_it_rejoined_is_a_false_suspicion():
    # Fault 0 killed master (declared at 1.03); master relaunched re-joined at 6.0; declared failed again
    # at 6.4, before the runner saw the pair whole (7.0): nothing touched it then.
    records = [record(0, 1.0, 7.0, {'master'})]
    verdicts = [Verdict(1.03, 'slave', 'master', 'silent'), Verdict(6.4, 'slave', 'master', 'silent again')]
    rejoins = [(6.0, 'master'), (6.1, 'slave')]
    explained, false, detections = judge(verdicts, records, rejoins)
    assert [v.reason for v in explained] == ['silent'] and [v.reason for v in false] == ['silent again']
    assert judge(verdicts, records)[1] == []                     # without the re-joins: hidden
    assert summary(verdicts, records, rejoins)['false_suspicions'] == 1
    # A re-join before the fault ends nothing.
    assert judge(verdicts, records, [(0.5, 'master')])[1] == []


def test_the_rejoin_alarm_is_read_by_its_words():
    assert rejoin_of('peer_watched', 'site master re-joined (epoch 4): watched again') == 'master'
    assert rejoin_of('peer_back', 'site master, declared failed, is heard again') is None
    assert rejoin_of('peer_watched', 'garbage') is None


def test_a_false_suspicion_carries_what_its_detector_said_when_it_heard_that_site_again():
    detail = ('site master, declared failed, is heard again (pid 7 on vm): it must re-join before it may serve '
              'or be promoted; the sender stalled: its next beat (seq 42) was sent 45.0 ms after the last one heard')
    assert heard_again_of('peer_back', detail) == 'master'
    assert heard_again_of('peer_watched', 'site master re-joined (epoch 4): watched again') is None
    heard = [(200.0, 'master', 'long after'), (99.0, 'master', 'before it'), (100.08, 'slave', 'the other site'),
             (100.05, 'master', detail)]
    s = summary([Verdict(100.03, 'slave', 'master', 'no heartbeat for 31.2 ms')], [], (), heard)
    [false] = s['false']
    assert false['then'] == detail
    assert format_summary(s, 0.03)[1].endswith('heard again: ' + detail)
    assert summary([Verdict(100.03, 'slave', 'master', 'x')], [])['false'][0]['then'] is None


def test_a_site_a_fault_blinded_may_declare_its_peer_and_that_is_no_false_suspicion():
    # Partitioned, the backup declares the primary failed (its own side of the cut); a kill of the backup's
    # Before does not blind its crash detector: a verdict by it about the primary then is a false suspicion.
    records = [dict(record(0, 10.0, 18.0, {'slave'}, kind='partition'), target='backup'),
               dict(record(1, 20.0, 28.0, {'slave'}, kind='kill'), target='backup/before'),
               dict(record(2, 30.0, 38.0, {'slave'}, kind='freeze_node'), target='backup/crash_detector')]
    verdicts = [Verdict(10.03, 'slave', 'master', 'cut off'), Verdict(20.05, 'slave', 'master', 'not blinded'),
                Verdict(31.0, 'slave', 'master', 'thawed detector')]
    explained, false, detections = judge(verdicts, records)
    assert [v.reason for v in explained] == ['cut off', 'thawed detector']
    assert [v.reason for v in false] == ['not blinded']
    assert detections == {}                      # neither times its fault: the site declared is not the one hit


def test_verdicts_the_runner_could_not_hear_are_read_from_the_sites_logs():
    lines = ['[WARN] [1795676798.580123]: /slave/crash_detector: site master failed: no heartbeat for 31.5 ms (timeout 30.0 ms)',
             '[WARN] [1795676798.700000]: /slave/after: pbr alone: slave goes on ALONE',
             '[WARN] [1795676799.000000]: /master/crash_detector: site slave failed: it announced its fail-stop: x']
    logged = logged_verdicts(lines)
    assert [(v.reporter, v.failed) for v in logged] == [('slave', 'master'), ('master', 'slave')]
    heard = [Verdict(1795676799.01, 'master', 'slave', 'it announced its fail-stop: x')]
    merged = merge(heard, logged)
    assert len(merged) == 2 and merged[0].reporter == 'slave' and heard[0] in merged


def test_one_verdict_logged_and_heard_apart_under_load_is_counted_once():
    """The detector logs its verdict, then stamps its report: stalled in between (a loaded machine), the
    two stamps were 131 ms apart in a campaign, and the one verdict was counted as two false suspicions."""
    reason = 'no heartbeat for 105.0 ms, of which 70.8 ms this detector was stalled (timeout 30.0 ms)'
    heard = [Verdict(1795951597.677, 'master', 'slave', reason)]
    logged = [Verdict(1795951597.546, 'master', 'slave', reason),
              Verdict(1795951597.600, 'master', 'slave', 'no heartbeat for 31.0 ms (timeout 30.0 ms)'),
              Verdict(1795951603.0, 'master', 'slave', reason)]
    assert merge(heard, logged) == sorted(heard + logged[1:])   # another verdict, or the same words much later
    # Two verdicts in the same words 1 s apart, one heard, both logged: two verdicts, not one.
    announced = 'it announced its fail-stop: the required node /slave/bank_server died'
    heard = [Verdict(10.0, 'master', 'slave', announced)]
    logged = [Verdict(10.0, 'master', 'slave', announced), Verdict(11.0, 'master', 'slave', announced)]
    assert merge(heard, logged) == [heard[0], logged[1]]


def test_a_readmission_before_the_repair_does_not_end_the_faults_window():
    # The killed backup, excluded, re-admitted by a join in flight (epoch 10) before the runner relaunched
    # it, then declared failed again: still the fault's doing. A re-join after the relaunch ends the window.
    rec = dict(record(0, 1.0, 9.0, {'slave'}), repaired_from=1.4)
    verdicts = [Verdict(1.03, 'master', 'slave', 'first'), Verdict(1.09, 'master', 'slave', 'again'),
                Verdict(6.5, 'master', 'slave', 'after its re-join')]
    explained, false, _ = judge(verdicts, [rec], rejoins=[(1.06, 'slave'), (6.0, 'slave')])
    assert [v.reason for v in explained] == ['first', 'again'] and [v.reason for v in false] == ['after its re-join']
