"""A benchmark's failover sample, drawn again when a false suspicion came before its fault
(aft_examples.ros.deployment: redrawn_sample, unless_pair_changed). No ROS master needed."""
import collections

import pytest

from aft_examples.ros import deployment

Pair = collections.namedtuple('Pair', 'primary backup epoch')


def test_a_sample_is_drawn_again_in_a_fresh_directory_until_one_is_measured():
    drawn = []

    def draw(directory):
        drawn.append(directory)
        return None if len(drawn) < 3 else {'failover_s': 0.04}
    sample, again = deployment.redrawn_sample(draw, '/tmp/x/crash00', tries=3)
    assert sample == {'failover_s': 0.04}
    assert drawn == ['/tmp/x/crash00', '/tmp/x/crash00_again1', '/tmp/x/crash00_again2']
    assert again == drawn[:2]


def test_a_sample_measured_at_once_is_not_drawn_again():
    assert deployment.redrawn_sample(lambda d: 0.0, '/tmp/x/a') == (0.0, [])   # 0.0 is a sample, not None


def test_too_many_redraws_raise_naming_the_logs():
    drawn = []
    with pytest.raises(RuntimeError, match=r'3 deployments in a row .*/tmp/x/k01\*'):
        deployment.redrawn_sample(lambda d: drawn.append(d), '/tmp/x/k01', tries=3)
    assert len(drawn) == 3


def test_the_fault_runs_only_while_the_witness_names_the_same_pair(monkeypatch):
    now = {'status': Pair('master', 'slave', 3)}
    monkeypatch.setattr(deployment, 'witness_status', lambda service: now['status'])
    injected = []
    fault = deployment.unless_pair_changed(lambda: injected.append(1) or (1, 0.0), ('master', 'slave', 3))
    assert fault() == (1, 0.0) and injected == [1]
    for changed, said in ((Pair('master', '', 4), r'master/slave, epoch 3, then master/, epoch 4'), (Pair('master', 'slave', 5), 'epoch 5'),
                          (None, 'no answer from the witness')):
        now['status'] = changed
        with pytest.raises(deployment.PairChanged, match=said):
            fault()
    assert injected == [1]   # never injected on a changed pair


def test_a_benchmark_whose_backup_was_excluded_and_admitted_again_measured_something_else(monkeypatch):
    monkeypatch.setattr(deployment, 'witness_status', lambda service: Pair('master', 'slave', 5))
    deployment.require_same_pair(('master', 'slave', 5), '/tmp/logs')   # the same pair: no error
    with pytest.raises(RuntimeError, match=r'master/slave, epoch 3, then master/slave, epoch 5.*/tmp/logs'):
        deployment.require_same_pair(('master', 'slave', 3), '/tmp/logs')


def test_without_a_witness_the_fault_runs_only_while_no_crash_detector_suspects_its_peer(monkeypatch):
    """Session 48's clean-clone CI: both detectors of a no-witness pair declared each other failed while they
    started (30 ms, a loaded machine); MASTER was then powered off, nobody was promoted, and the healing
    benchmark's calls waited for ever. The fault is not injected then (PairChanged: drawn again)."""
    import rospy
    Status = collections.namedtuple('Status', 'alive state why')
    views = {'/master/crash_detector/peer_status': Status(True, 'ALIVE', ''),
             '/slave/crash_detector/peer_status': Status(True, 'ALIVE', '')}

    class Proxy(object):
        def __init__(self, service, _type):
            self.service = service

        def __call__(self):
            if self.service not in views:
                raise rospy.ServiceException('no provider')
            return views[self.service]
    monkeypatch.setattr(rospy, 'ServiceProxy', Proxy)
    injected = []
    fault = deployment.unless_peer_suspected(lambda: injected.append(1) or (1, 0.0))
    assert fault() == (1, 0.0) and injected == [1]
    views['/slave/crash_detector/peer_status'] = Status(False, 'FAILED', 'master declared failed; heard again')
    with pytest.raises(deployment.PairChanged, match='slave/crash_detector.*master declared failed'):
        fault()
    del views['/master/crash_detector/peer_status']
    assert 'did not answer' in deployment.peer_suspicion()
    assert injected == [1]
