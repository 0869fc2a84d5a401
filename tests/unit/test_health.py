"""The health FTM nodes report on /diagnostics and the one line per site `rosrun aft_ftm status` prints."""
from aft_ftm import health
from aft_ftm.health import Level
from aft_ftm.protocol import Role


def test_a_primary_with_its_backup_is_ok_alone_is_degraded_deposed_cannot_serve():
    ok = health.replica_after('master', 'pbr', Role.PRIMARY, 2, 'slave', held=1)
    assert ok.level == Level.OK and ok.value('epoch') == '2' and ok.value('held') == '1'
    alone = health.replica_after('master', 'pbr', Role.ALONE, 3, 'slave')
    assert alone.level == Level.WARN and 'alone' in alone.message
    deposed = health.replica_after('master', 'lfr', Role.PRIMARY, 3, 'slave', stopped='deposed: slave serves')
    assert deposed.level == Level.ERROR and 'deposed' in deposed.message


def test_a_backup_that_cannot_take_over_is_degraded_and_says_why():
    joining = health.replica_after('slave', 'pbr', Role.BACKUP, 1, 'master', cannot_take_over='holds no state yet')
    assert joining.level == Level.WARN and 'holds no state yet' in joining.message
    assert health.replica_after('slave', 'pbr', Role.BACKUP, 2, 'master').level == Level.OK


def test_protocol_and_detector_levels():
    assert health.protocol('m', Role.ALONE, 3, 5, 900, 1000, 0).level == Level.OK
    full = health.protocol('m', Role.ALONE, 3, 5, 1000, 1000, 0)
    assert full.level == Level.WARN and 'refusing' in full.message
    assert health.protocol('m', Role.ALONE, 3, 5, 10, 0, 0, hung='/proxy/4').level == Level.ERROR
    assert health.detector('m', 's', 'ALIVE', 0.004).level == Level.OK
    assert health.detector('m', 's', 'FAILED', 2.0).level == Level.WARN
    assert health.detector('m', 's', 'ALIVE', 0.004, stopped='server hangs').level == Level.ERROR


def test_summary_is_one_line_per_site_with_its_worst_level_and_why():
    reports = {
        '/master/after': health.replica_after('master', 'pbr', Role.ALONE, 3, 'slave'),
        '/master/protocol': health.protocol('master', Role.ALONE, 3, 2, 200, 1000, 0),
        '/master/crash_detector': health.detector('master', 'slave', 'FAILED', 3.0),
        '/slave/after': health.replica_after('slave', 'pbr', Role.BACKUP, 2, 'master', stopped='fail-stop'),
    }
    lines = health.summary(reports)
    assert [(site, level) for site, level, _ in lines] == [('master', Level.WARN), ('slave', Level.ERROR)]
    master = lines[0][2]
    assert 'pbr' in master and 'ALONE' in master and 'epoch 3' in master
    assert 'after: alone' in master and 'crash_detector: peer slave declared failed' in master


def test_recovery_reports_its_last_failover_and_a_failed_one_as_an_error():
    assert health.recovery('slave', Role.BACKUP, 1).message == 'no failover yet'
    last = {'failed_site': 'master', 'reason': 'no heartbeat for 31 ms', 'ok': True, 'seconds': 0.0123,
            'steps': [{'step': 'FAIL_SILENCE', 'ok': True, 'detail': '', 'seconds': 0.002}]}
    done = health.recovery('slave', Role.ALONE, 2, last)
    assert done.level == Level.OK and 'master failed (no heartbeat for 31 ms); recovered in 12.3 ms' in done.message
    assert 'FAIL_SILENCE 2.0 ms' in done.message and done.value('last_recovery_ms') == '12.3'
    failed = dict(last, ok=False, steps=[{'step': 'PROMOTE_PROTOCOL', 'ok': False, 'detail': 'refused', 'seconds': 0.1}])
    report = health.recovery('slave', Role.ALONE, 2, failed)
    assert report.level == Level.ERROR and 'PROMOTE_PROTOCOL: refused' in report.message
    assert health.recovery('slave', None, 3, last).level == Level.WARN


def test_proxy_warns_of_a_request_nobody_answers_and_of_its_bound():
    ok = health.proxy('/account', 2, 0.1, 3, 0, 100, 1000, 4, patience=2.0)
    assert ok.level == Level.OK and ok.message == '2 pending, 3 re-sent, 0 refused' and ok.value('site') == '/account'
    late = health.proxy('/account', 1, 2.5, 5, 0, 100, 1000, 4, patience=2.0)
    assert late.level == Level.WARN and 'unanswered for 2.5 s' in late.message
    assert health.proxy('/account', 9, 0.1, 0, 0, 1000, 1000, 4, patience=2.0).level == Level.WARN


def test_a_nested_mechanism_s_node_counts_for_the_site_of_its_name_space():
    lines = health.summary({'/master/tr/protocol': health.protocol('', Role.ALONE, 0, 1, 10, 0, 0),
                            '/master/after': health.replica_after('master', 'pbr', Role.PRIMARY, 2, 'slave')})
    assert [site for site, _, _ in lines] == ['master']


def test_a_stage_reports_a_late_server_call_and_a_fail_stop_and_any_node_is_degraded_while_suspended():
    assert health.stage('tr', 'before').level == Level.OK
    calling = health.stage('', 'proceed', calling_for=0.2, patience=5.0)
    assert calling.level == Level.OK and calling.value('calling_for_s') == '0.200'
    late = health.stage('', 'proceed', calling_for=7.5, patience=5.0)
    assert late.level == Level.WARN and 'not answered for 7.5 s' in late.message
    failed = health.stage('', 'proceed', calling_for=7.5, patience=5.0, failed='the server hangs')
    assert failed.level == Level.ERROR and 'the server hangs' in failed.message
    open_ = health.with_suspension(health.stage('tr', 'after'), 'OPEN', 0)
    assert open_.level == Level.OK and open_.value('suspension') == 'OPEN'
    held = health.with_suspension(health.stage('tr', 'after'), 'CLOSED', 3)
    assert held.level == Level.WARN and held.message.startswith('suspended (closed, 3 message(s) held)')
    # Suspension never hides something worse.
    assert health.with_suspension(failed, 'CLOSED', 0).level == Level.ERROR


def test_the_witness_is_degraded_while_a_primary_serves_alone():
    ok = health.witness(4, 'master', 'slave', 'admitted slave', persistent=True)
    assert ok.level == Level.OK and ok.value('state_file') == 'yes'
    alone = health.witness(5, 'slave', '', 'excluded master', persistent=False)
    assert alone.level == Level.WARN and 'slave serves alone' in alone.message
    assert health.witness(0, '', '', 'start', persistent=False).level == Level.OK   # nobody registered yet


def test_sec_gate_and_watchdog_levels():
    assert health.sec_gate('server', 'server', Role.PRIMARY, 1, 0, 0).level == Level.OK
    rejected = health.sec_gate('client', 'client', Role.PRIMARY, 1, 2, 3)
    assert rejected.level == Level.WARN and '3 message(s) rejected' in rejected.message
    assert health.watchdog('board_a', 'board_b', 0, 'a primary, b backup').level == Level.OK
    assert health.watchdog('board_b', None, 1, 'a lost, b primary').level == Level.WARN
    assert health.watchdog(None, None, 2, 'both lost').level == Level.ERROR
    # They count in `status` under a site of their own.
    lines = health.summary({'/aft/witness': health.witness(5, 'slave', '', 'x', False),
                            '/ftm/watchdog': health.watchdog('board_a', 'board_b', 0, 'd')})
    assert [(site, level) for site, level, _ in lines] == [('watchdog', Level.OK), ('witness', Level.WARN)]


def test_a_proceed_says_whether_it_is_calling_the_server_or_idle():
    idle = health.stage('pbr', 'proceed', None, 5.0, None)
    busy = health.stage('pbr', 'proceed', 0.25, 5.0, None)
    assert idle.level == busy.level == health.Level.OK
    assert 'idle' in idle.message and 'calling' not in idle.message
    assert 'calling the server' in busy.message and '0.250' in busy.message


def test_recovery_warns_while_the_master_is_unreachable():
    report = health.recovery('slave', Role.ALONE, 2, None, master_unreachable_for=12.4)
    assert report.level == Level.WARN and report.message.startswith('master_unreachable')
    assert report.value('master') == 'unreachable for 12 s'
    assert health.recovery('slave', Role.ALONE, 2).value('master') == 'reachable'
