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
