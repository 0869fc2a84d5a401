"""The benchmark report (aft_bench.report): verdicts computed from figures, never assumed; every
section present whatever ran; consistency checks that catch figures that do not add up."""
import copy
import json
import os

import pytest

from aft_bench import report, report_plots


def buffering_row(lost, sent=200, stop=1.0, queue=1, size=100):
    return {'payload': 'small', 'payload_bytes': size, 'queue_size': queue, 'stop_s': stop, 'repeats': 1,
            'sent': sent, 'received': sent - lost, 'lost': lost, 'lost_pct': 100.0 * lost / sent,
            'dropped_by_publisher_queue': 0, 'dropped_by_subscriber_queue': lost}


def adaptation_run(mode, requests=100, correct=100, lost=None, ok=True):
    return {'adaptation': 'compose PBR->PBR+TR', 'mode': mode, 'ok': ok, 'requests': requests,
            'checker': {'correct': correct}, 'lost': requests - correct if lost is None else lost, 'duplicated': 0,
            'state_ok': True, 'client_pause_s': 0.04 if mode == 'prepared' else 2.0,
            'timeline': [[-0.1, 0.001, True], [0.0, 0.03, True], [0.5, 0.001, True]], 'adaptation_end_s': 0.4}


def adaptation_row(mode):
    return {'adaptation': 'compose PBR->PBR+TR', 'mode': mode, 'client_pause_s': 0.04 if mode == 'prepared' else 2.0,
            'engine_pause_s': 0.03 if mode == 'prepared' else 1.9, 'duration_s': 2.0, 'lost': 0, 'duplicated': 0,
            'state_ok': 1, 'runs': 1, 'failed': 0, 'nodes_touched': 12}


def mechanism(median, r2r, cpu, hops=6):
    chain = {'hops': hops, 'rounds': 4, 'median_s': 0.0006, 'p99_s': 0.001, 'config_median_s': median,
             'ratio': median / 0.0006} if hops else None
    return {'median_s': median, 'p99_s': median * 2, 'hops': hops, 'client_replica_bytes': 176,
            'replica_replica_bytes': r2r, 'cpu_s_per_request': cpu, 'table_one': None, 'chain': chain}


def car_run(hazards, ok=True, ratio=0.9):
    return {'ok': ok, 'problems': [], 'hazards': hazards, 'min_gap_ratio': ratio, 'failovers': [],
            'faults_injected': 10, 'faults_masked': 8, 'safe_stop_at': None,
            'collision_at': 8.5 if 'collision' in hazards else None}


def sm_period(share, detect_n=2, missed=0):
    stat = {'n': detect_n, 'median_ms': 5.0, 'min_ms': 4.0, 'max_ms': 6.0}
    fault = {'detect': stat, 'restart': stat, 'recovery': stat, 'kinds': ['exit'], 'missed': missed}
    return {'faults': {'crash': dict(fault), 'hang': dict(fault)}, 'warm': {'crash': dict(fault), 'hang': dict(fault)},
            'com_ms': 0.3,
            'cpu': {'channel': 'local', 'manager_cpu_percent': 0.2, 'services_cpu_percent': 7.0,
                    'manager_share_percent': share, 'manager_of_services_percent': share},
            'cpu_ros': {'channel': 'ros', 'manager_cpu_percent': 6.8, 'services_cpu_percent': 23.0,
                        'manager_share_percent': 23.0, 'manager_of_services_percent': 29.6}}


def calls(sent, answered):
    return {'sent': sent, 'answered': answered, 'correct': answered, 'lost': sent - answered, 'median_s': 0.001}


@pytest.fixture
def figures():
    return {
        'machine': {'cpus': 2, 'cpu_model': 'test cpu'}, 'mode': 'quick', 'started': 'now', 'elapsed_s': 10,
        'steps': {'pbr': {'command': 'scripts/bench_pbr', 'exit': 0, 'seconds': 1, 'log': 'pbr.log', 'ok': True}},
        'pbr': {'period_s': 0.01, 'timeout_s': 0.03,
                'latency': {'PBR': {'median_s': 0.001, 'p99_s': 0.002, 'ratio_to_chain': 1.3}},
                'failover': {'crashes': 2, 'median_s': 0.04, 'p99_s': 0.05, 'max_s': 0.05, 'detection_median_s': 0.03,
                             'recovery_median_s': 0.01, 'wrong_replies': 0},
                'failover_samples': [{'failover_s': 0.04, 'detection_s': 0.03, 'recovery_s': 0.01, 'wrong': 0},
                                     {'failover_s': 0.05, 'detection_s': 0.03, 'recovery_s': 0.01, 'wrong': 0}]},
        'mechanisms': {'calls': 10, 'order': ['direct call', 'TR', 'PBR', 'LFR'],
                       'configs': {'direct call': mechanism(0.0001, 0, {'site': 0.00004}, hops=None),
                                   'TR': mechanism(0.001, 0, {'site': 0.001}),
                                   'PBR': mechanism(0.001, 195, {'client': 0.0001, 'master': 0.0006, 'slave': 0.0002}),
                                   'LFR': mechanism(0.0008, 147, {'client': 0.0001, 'master': 0.0005, 'slave': 0.0004})}},
        'adaptation': {'rows': [adaptation_row('prepared'), adaptation_row('paper')],
                       'runs': [adaptation_run('prepared'), adaptation_run('paper')]},
        'buffering': {'rate_hz': 100, 'rows': [buffering_row(0, stop=0.1), buffering_row(98)], 'conclusions': []},
        'service_manager': {'repeats': 2, 'periods': {'0.001': sm_period(30.0), '0.01': sm_period(31.0)},
                            'roslaunch_respawn': {'crash_spawned': {'n': 1, 'median_ms': 40.0},
                                                  'crash_recovery': {'n': 1, 'median_ms': 450.0},
                                                  'hang_detected_within_5s': False},
                            'condition': {'0.001': {'detect_restart_com_ms': 450.0,
                                                    'fits': {'C4G': False, 'OmsCom': False},
                                                    'detect_alone_fits': {'C4G': False, 'OmsCom': True}}},
                            'condition_cold': {'0.001': {'detect_restart_com_ms': 500.0,
                                                         'fits': {'C4G': False, 'OmsCom': False},
                                                         'detect_alone_fits': {'C4G': False, 'OmsCom': True}}}},
        'car': {'rows': [{'entity': 'laser', 'failure_mode': 'inconsistent data', 'mechanism': 'triplication_vote',
                          'scenario': 'laser_value_faults', 'hazard': 'collision',
                          'with': car_run([]), 'without': car_run(['collision'], ok=False)}],
                'series': {'scenario': 'laser_value_faults', 'with': [[0, 10, 5], [1, 9, 5]],
                           'without': [[0, 10, 5], [1, 0, 5]]}},
        'master': {'master_down': {'established_service': calls(50, 50),
                                   'established_topic': {'sent': 100, 'received': 100, 'lost': 0},
                                   'new_service_lookup': {'ok': False, 'seconds': 1.0, 'error': 'unable to contact'},
                                   'new_subscription': {'ok': False, 'received': 0, 'error': ''},
                                   'new_node': {'ok': False, 'seconds': 5.0, 'error': 'not registered'},
                                   'ftm_failover': dict(calls(40, 40), longest_wait_s=0.05, backup_serving=True,
                                                        error='')},
                   'master_restarted': {'restart_s': 1.5, 'old_nodes_registered': {'before_crash': 12, 'after_1s': 0,
                                                                                   'after_5s': 0, 'names_missing': []},
                                        'established_service': calls(50, 50),
                                        'new_service_lookup': {'ok': False, 'seconds': 0.1, 'error': 'no provider'},
                                        'new_subscription': {'ok': False, 'received': 0, 'error': ''},
                                        'new_nodes': {'ok': True, 'received': 10, 'error': ''}}},
    }


def verdicts(figures):
    return {c['key']: c['verdict'] for c in report.claims(figures)}


def test_every_section_is_present_even_when_nothing_ran():
    text = report.build({'steps': {}})
    for title in report.SECTIONS:
        assert '## %s\n' % title in text
    assert all(v == report.NOT_MEASURED for v in verdicts({}).values())


def test_a_failed_step_is_named_with_its_log():
    f = {'steps': {'master': {'exit': 2, 'log': '/tmp/logs/master.log', 'ok': False}}}
    claim = next(c for c in report.claims(f) if c['key'] == 'master_spof')
    assert claim['verdict'] == report.NOT_MEASURED
    assert 'exit 2' in claim['condition'] and '/tmp/logs/master.log' in claim['condition']


def test_verdicts_follow_the_figures(figures):
    v = verdicts(figures)
    assert v['ros_buffers'] == report.REFUTED            # a configuration lost messages
    assert v['adaptation_loses_nothing'] == report.CONFIRMED
    assert v['bandwidth'] == report.QUALIFIED            # 195 / 147 < 2
    assert v['cpus'] == report.QUALIFIED                 # PBR's backup < half the primary's CPU
    assert v['failover'] == report.CONFIRMED
    assert v['availability_condition'] == report.QUALIFIED
    assert v['overhead'] == report.REFUTED               # 30 % > 10 %
    assert v['hang_detection'] == report.CONFIRMED
    assert v['laser_vote'] == report.CONFIRMED
    assert v['pbr_boards'] == report.NOT_MEASURED        # that row did not run
    assert v['master_spof'] == report.QUALIFIED


def test_verdicts_change_with_the_figures(figures):
    f = copy.deepcopy(figures)
    f['buffering']['rows'] = [buffering_row(0), buffering_row(0, stop=5.0)]
    f['adaptation']['runs'][0] = adaptation_run('prepared', correct=97)
    f['mechanisms']['configs']['PBR']['replica_replica_bytes'] = 1000
    f['service_manager']['periods'] = {'0.01': sm_period(8.0)}
    f['pbr']['failover']['wrong_replies'] = 1
    f['car']['rows'][0]['with'].update(hazards=['collision'], collision_at=9.0)
    v = verdicts(f)
    assert v['ros_buffers'] == report.CONFIRMED
    assert v['adaptation_loses_nothing'] == report.REFUTED
    assert v['bandwidth'] == report.CONFIRMED
    assert v['overhead'] == report.CONFIRMED
    assert v['failover'] == report.REFUTED
    assert v['laser_vote'] == report.REFUTED
    # a hazard that also stays away without the mechanism does not confirm the mechanism
    f['car']['rows'][0]['with']['hazards'] = []
    f['car']['rows'][0]['without']['hazards'] = []
    assert verdicts(f)['laser_vote'] == report.QUALIFIED


def test_lost_requests_are_sent_minus_answered(figures):
    f = copy.deepcopy(figures)
    f['adaptation']['runs'][1] = adaptation_run('paper', requests=120, correct=117)
    text = report.build(f)
    row = next(line for line in text.split('\n') if line.startswith('| compose PBR->PBR+TR | paper'))
    cells = [c.strip() for c in row.split('|')]
    assert cells[6:9] == ['120', '117', '3']
    assert all(ok for _, ok, _ in report.consistency(f))


def test_consistency_catches_figures_that_do_not_add_up(figures):
    f = copy.deepcopy(figures)
    f['adaptation']['runs'][0]['lost'] = 0
    f['adaptation']['runs'][0]['checker']['correct'] = 90          # 100 sent, 90 answered, 0 lost?
    f['master']['master_down']['ftm_failover']['lost'] = 0
    f['master']['master_down']['ftm_failover']['answered'] = 30
    f['pbr']['failover_samples'].pop()
    failed = [name for name, ok, _ in report.consistency(f) if not ok]
    assert any(name.startswith('adaptation compose') for name in failed)
    assert any('ftm_failover' in name for name in failed)
    assert 'failover: one sample per crash' in failed
    assert '**FAILED**: failover: one sample per crash' in report.build(f)


def test_targets_are_judged(figures):
    met = {t: ok for t, _, ok in report.targets(figures)}
    assert len(met) == 4 and all(met.values())
    f = copy.deepcopy(figures)
    f['pbr']['failover']['median_s'] = 0.07
    assert not next(ok for t, _, ok in report.targets(f) if t.startswith('failover median'))


def test_plots_are_drawn_from_the_figures(figures, tmp_path):
    drawn = report_plots.draw_all(json.loads(json.dumps(figures)), str(tmp_path))
    assert sorted(drawn) == ['adaptation', 'car', 'failover', 'latency']
    for name in drawn.values():
        with open(os.path.join(str(tmp_path), name), 'rb') as f:
            assert f.read(8) == b'\x89PNG\r\n\x1a\n'
    assert report_plots.draw_all({}, str(tmp_path)) == {}


def test_partial_figures_cost_their_section_not_the_report(figures):
    f = copy.deepcopy(figures)
    # the master could not be restarted: bench_master wrote no restart figures
    f['master']['master_restarted'] = {'restart_s': None, 'error': 'roscore did not answer'}
    f['mechanisms']['configs']['TR']['p99_s'] = None
    f['car']['rows'][0]['without'] = {'error': 'no summary (exit 2); log car.log'}
    text = report.build(f)
    for title in report.SECTIONS:
        assert '## %s\n' % title in text
    claims = {c['key']: c for c in report.claims(f)}
    assert claims['master_spof']['verdict'] == report.NOT_MEASURED
    assert 'incomplete' in claims['master_spof']['condition']
    assert claims['laser_vote']['verdict'] == report.NOT_MEASURED
    assert 'no summary (exit 2)' in claims['laser_vote']['condition']
    assert '| TR | 1.000 ms | n/a | 10.0 | 6 | 1.000 ms against 0.600 ms | 1.67 |' in text   # a missing p99 shown
    assert '**FAILED**: figures complete enough to check' in text


def test_a_run_the_benchmark_could_not_set_up_is_not_evidence(figures):
    f = copy.deepcopy(figures)
    broken = adaptation_run('paper', requests=0, correct=0, ok=False)
    broken.update(error='benchmark run failed: RuntimeError: replica master did not come up', state_ok=False,
                  checker=None)
    f['adaptation']['runs'].append(broken)
    claim = next(c for c in report.claims(f) if c['key'] == 'adaptation_loses_nothing')
    assert claim['verdict'] == report.CONFIRMED
    assert '1 run(s) the benchmark could not set up left out' in claim['measured']


def test_the_server_count_must_agree_with_the_lost_requests(figures):
    f = copy.deepcopy(figures)
    run = f['adaptation']['runs'][0]
    run['state'] = {'master': [100, 100, 'digest']}
    assert all(ok for _, ok, _ in report.consistency(f))
    run['state']['master'][1] = 99   # the server applied one operation fewer than the client says
    failed = [name for name, ok, _ in report.consistency(f) if not ok]
    assert failed == ['adaptation compose PBR->PBR+TR (prepared): operations the server applied = sent - lost']


def campaign_figures(violations=(), false_suspicions=0, failover_ms=41.0):
    table = [('kill', 3, '2 failover, 1 restarted', 180.0, 300.0, 300.0),
             ('power_loss', 2, '1 failover, 1 restarted', 60.0, 70.0, 70.0),
             ('all', 5, '3 failover, 2 restarted', 100.0, 300.0, 300.0)]
    return {'seed': 9, 'faults': 5, 'faults_run': 5, 'clients': 2, 'per_segment': 5, 'mechanisms': ['pbr', 'lfr'],
            'backend': 'ProcessBackend', 'hosts': '', 'elapsed_s': 20.0, 'calls': {'ok': 900, 'error': 12},
            'detection_timeout_s': 0.03, 'violations': list(violations), 'table': table,
            'detection': {'verdicts': 3 + false_suspicions, 'explained': 3, 'false_suspicions': false_suspicions,
                          'false': [], 'detection_ms_median': 27.0, 'detection_ms_by_kind': {'power_loss': 26.0},
                          'failover_unavailable_ms_median': failover_ms, 'failovers': 3}}


def test_the_campaign_section_and_its_targets_follow_its_figures(figures):
    f = dict(copy.deepcopy(figures), campaign=campaign_figures())
    text = report.build(f)
    section = text.split('## Campaign')[1].split('\n## ')[0]
    assert '| power_loss | 2 | 1 failover, 1 restarted | 60 ms | 70 ms | 70 ms |' in section
    assert 'Violations: none.' in section and '**0 false suspicions**' in section
    met = {t.split(' (')[0]: ok for t, _, ok in report.targets(f) if t.startswith('campaign')}
    assert met == {'campaign: every answered operation exactly once, in real-time order': True,
                   'campaign: failover median < 50 ms with 0 false suspicions': True}
    bad = dict(f, campaign=campaign_figures(violations=[{'segment': 0, 'kind': 'lost', 'detail': 'client1#4',
                                                         'replay': 'x'}], false_suspicions=2))
    assert not any(ok for t, _, ok in report.targets(bad) if t.startswith('campaign'))
    assert 'segment 0 lost: client1#4' in report.build(bad)
    assert [name for name, ok, _ in report.consistency(bad) if not ok] == []
    broken = copy.deepcopy(f)
    broken['campaign']['faults_run'] = 6
    assert 'campaign: faults by kind add up to the faults run' in [n for n, ok, _ in report.consistency(broken) if not ok]


def test_a_campaign_that_did_not_run_is_said_missing(figures):
    text = report.build(figures)
    assert '## Campaign: seeded faults against the bank, checked by its history' in text
    assert not [t for t, _, _ in report.targets(figures) if t.startswith('campaign')]


def test_the_service_manager_section_sets_the_designs_side_by_side(figures):
    text = '\n'.join(report.service_manager_lines(figures))
    assert '| 1 ms | cold restart |' in text and '| 1 ms | warm spare |' in text
    assert 'roslaunch respawn' in text
    assert 'ROS heartbeats: manager' in text and 'local channel: manager' in text and '29.6 %' in text
    assert 'warm spare, crash' in text and 'cold restart, crash' in text
    claim = [c for c in report.claims(figures) if c['key'] == 'overhead'][0]
    assert 'local channel' in claim['measured'] and 'with ROS heartbeats: 30 %' in claim['measured']
    condition = [c for c in report.claims(figures) if c['key'] == 'availability_condition'][0]
    assert condition['measured'].startswith('warm spare:') and 'cold restart: 500 ms' in condition['measured']


def state_run(size, incremental, per_request, identical=True):
    return {'state_bytes': size, 'incremental': incremental, 'requests': 50, 'bytes_per_request': per_request,
            'checkpoints': 50, 'latency_median_s': 0.007, 'latency_p99_s': 0.02, 'backup_state_identical': identical,
            'replies_right': True}


def test_the_large_state_section_and_its_target_follow_the_figures(figures):
    figures['state'] = {'runs': [state_run(1000061, False, 1010216.0), state_run(1000061, True, 275.0)]}
    text = report.build(figures)
    assert '| 1000061 B | incremental | 275 |' in text
    target = [t for t in report.targets(figures) if 'bytes between replicas' in t[0]]
    assert target and target[0][1:] == ('275 B', True)
    figures['state']['runs'][1] = state_run(1000061, True, 275.0, identical=False)
    assert [t[2] for t in report.targets(figures) if 'bytes between replicas' in t[0]] == [False]
    figures['state']['runs'][1] = state_run(1000061, True, 4000.0, identical=False)
    assert [t[2] for t in report.targets(figures) if 'bytes between replicas' in t[0]] == [False]
    assert '**no**' in report.build(figures)
    del figures['state']
    assert not [t for t in report.targets(figures) if 'bytes between replicas' in t[0]]


def clients_row(name, n, throughput, ratio=None):
    return {'configuration': name, 'clients': n, 'calls': int(throughput * 4), 'throughput_per_s': throughput,
            'latency_median_s': 0.004, 'latency_p99_s': 0.02, 'throughput_vs_direct': ratio,
            'requests_per_checkpoint': 3.5 if ratio is not None else None}


def test_the_concurrent_clients_section_its_target_and_its_plot_follow_the_figures(figures, tmp_path):
    figures['clients'] = {'seconds': 4.0, 'rows': [clients_row('direct', 8, 10000.0),
                                                   clients_row('PBR, max_batch 16', 8, 900.0, 0.09),
                                                   clients_row('PBR, max_batch 1', 8, 300.0, 0.03)]}
    figures['clients']['failovers'] = [{'clients': 4, 'failover_s': 0.0512, 'calls_across': 4}]
    text = report.build(figures)
    assert '| PBR, max_batch 16 | 8 | 900 |' in text and '| 9 % | 3.50 |' in text
    assert '4 clients 51.2 ms' in text
    target = [t for t in report.targets(figures) if '8 concurrent clients' in t[0]]
    assert target and target[0][2] is False and target[0][1].startswith('9 %')
    figures['clients']['rows'][1] = clients_row('PBR, max_batch 16', 8, 6000.0, 0.6)
    assert [t[2] for t in report.targets(figures) if '8 concurrent clients' in t[0]] == [True]
    assert report_plots.clients(figures, str(tmp_path / 'clients.png'))
    del figures['clients']
    assert not [t for t in report.targets(figures) if '8 concurrent clients' in t[0]]
    assert report_plots.clients(figures, str(tmp_path / 'none.png')) is None


def test_the_latency_ratio_over_runs_is_judged_9_of_10(figures):
    figures['pbr']['latency_runs'] = {'ratios': [1.1] * 9 + [1.4], 'at_most_1_3': 9}
    row = [t for t in report.targets(figures) if 'in at least 9 runs' in t[0]]
    assert row and row[0][2] and row[0][1].startswith('9 of 10')
    figures['pbr']['latency_runs'] = {'ratios': [1.1] * 8 + [1.4] * 2, 'at_most_1_3': 8}
    assert not [t for t in report.targets(figures) if 'in at least 9 runs' in t[0]][0][2]


def security_row(config, median_ms, cpu_ms):
    return {'config': config, 'calls': 300, 'median_ms': median_ms, 'p99_ms': median_ms * 3, 'cpu_ms_per_call': cpu_ms}


def test_the_security_section_follows_the_figures_against_its_unsecured_row(figures):
    figures['security'] = {'calls': 300, 'rows': [security_row('none', 2.0, 2.5), security_row('sec', 5.0, 7.5),
                                                  security_row('sec+tls', 6.0, 0.0)]}
    text = report.build(figures)
    assert '| SEC, replay log (synced) | 5.00 ms | 15.00 ms | 7.50 ms | 2.50x | 3.00x |' in text
    assert '| SEC + TLS | 6.00 ms | 18.00 ms | 0.00 ms | 3.00x | 0.00x |' in text
    figures['security']['rows'][0] = security_row('none', 2.0, 0.0)   # a run too short to count a CPU tick
    assert '| SEC, replay log (synced) | 5.00 ms | 15.00 ms | 7.50 ms | 2.50x | n/a |' in report.build(figures)
    assert '`sec-memory` against `sec`' not in report.build(figures)
    figures['security']['rows'].append({'config': 'sec-memory', 'error': 'exit 1: the deployment did not start'})
    text = report.build(figures)
    assert '| SEC, floors in memory | **failed**: exit 1: the deployment did not start |' in text
    assert '`sec-memory` against `sec`' in text
    figures['security']['rows'] = figures['security']['rows'][1:]
    assert '_Figures of `scripts/bench_security` incomplete' in report.build(figures)
    del figures['security']
    assert '_Not measured: `scripts/bench_security`' in report.build(figures)


def test_the_failover_section_says_how_many_samples_a_false_suspicion_made_draw_again(figures):
    figures['pbr']['samples_redrawn'] = 2
    assert '2 sample(s) drawn again in a fresh deployment' in report.build(figures)
    figures['pbr']['samples_redrawn'] = 0
    assert 'drawn again' not in report.build(figures)
    run = {'failover_s': 0.05, 'detection_s': 0.03, 'recovery_s': 0.02, 'vote_s': 0.001, 'exactly_once': True}
    figures['healing'] = {'failover': {'witness': [run], 'no_witness': [dict(run, vote_s=None)]},
                          'failover_samples_redrawn': ['the pair changed before the fault']}
    text = report.build(figures)
    assert '1 sample(s) with the witness drawn again' in text and '| with the witness | 1 | 50.0 ms |' in text
