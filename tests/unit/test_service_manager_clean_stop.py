"""A clean stop of the service manager keeps what it holds (review of session 34: it removed its
record, so a manager started again lifted a safe state and restarted services left down, as if
nothing had happened). The node is built without ROS (no master): its supervisor is real, its
process trees and publishers are fakes."""
import os
import threading

from aft_service_manager import trust
from aft_service_manager.services import State, Supervisor, parse_config


def config():
    return parse_config('services:\n  a: {command: x, critical: true}\n  b: {command: y}\n', source='test.yaml')


class _Trees(object):
    def leftovers(self):
        return []

    def close(self, timeout):
        pass


def _node(tmp_path, supervisor):
    from aft_service_manager.ros.service_manager_node import ServiceManagerNode
    node = ServiceManagerNode.__new__(ServiceManagerNode)
    node.unacted, node.counted, node.already_counted = {}, set(), set()   # (the set-up's lost instances)
    node.lock, node.children, node.spares, node.stopping = threading.RLock(), {}, {}, {}
    node.config = {'manager': {'kill_timeout': 0.1}}
    node.wake_r, node.wake_w = os.pipe()
    node.local, node.safe_pub, node.own_trees, node.tree = None, None, [], _Trees()
    node.supervisor = supervisor
    node.pid_file, node.record_file = str(tmp_path / 'm.pids'), str(tmp_path / 'm.record')
    node.own = {node.pid_file: trust.write_private_json(node.pid_file, {}),
                node.record_file: trust.write_private_json(node.record_file, supervisor.record())}
    return node


def _stop(node):
    node.shutdown()
    os.close(node.wake_r)
    os.close(node.wake_w)


def test_a_safe_state_and_services_left_down_survive_a_clean_stop_and_hold_at_the_next_start(tmp_path):
    sup = Supervisor(config())
    sup._escalate('a: restart limit exhausted', 0.0)
    sup['b'].held_down, sup['b'].starts = True, 1            # b: stopped by an operator
    node = _node(tmp_path, sup)
    _stop(node)
    assert not os.path.exists(node.pid_file)
    again = Supervisor(config())                             # the next manager of this name
    held = again.restore(trust.read_private_json(node.record_file), 0.0)
    assert again.safe_state.startswith("held from the manager's previous run: a: restart limit exhausted")
    assert held == ['b'] and again['b'].held_down
    ok, why = again.clear_safe_state(1.0)                    # still an operator's decision, as after a kill
    assert not ok and 'critical services not running: a' in why


def test_a_clean_stop_holding_nothing_leaves_no_record_and_the_next_start_is_afresh(tmp_path):
    sup = Supervisor(config())
    node = _node(tmp_path, sup)
    _stop(node)
    assert not os.path.exists(node.record_file) and not os.path.exists(node.pid_file)
    again = Supervisor(config())
    assert again.restore({}, 0.0) == [] and again.safe_state is None
    assert again['a'].state == State.STOPPED and not again['a'].held_down


def test_a_clean_stop_keeps_the_fault_counts_for_the_next_start(tmp_path):
    """A SIGTERM (rosnode kill, systemctl restart, a service killing its manager) is a clean stop:
    the record went with it unless something was held, and a service failing at every start got a
    fresh allowance and no back-off at each (review of session 38). Its counts are kept now."""
    sup = Supervisor(config())
    sup['a'].spawned(0.0)
    sup['a'].heard(0.1, 'ok')
    sup.fault('a', 'exit', 'status 1', 1.0)
    node = _node(tmp_path, sup)
    _stop(node)
    again = Supervisor(config())
    assert again.restore(trust.read_private_json(node.record_file), 2.0) == []
    assert again['a'].errors == {'exit': 1} and len(again['a'].restarts) == 1 and again.safe_state is None
