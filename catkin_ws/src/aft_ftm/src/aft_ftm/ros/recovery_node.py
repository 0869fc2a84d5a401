"""Recovery: fail-silence of the failed site, then failover or going on alone."""
import json
import os
import threading
import time

import psutil
import rospy
from aft_msgs.srv import Rebind, RebindRequest, SetNodes, SetNodesResponse, SetRole
from std_msgs.msg import String

from .. import config
from ..protocol import Role
from ..recovery import Step, plan, role_after, same_process
from ..sites import power_off, process_tree, this_host
from ..ports import SUBSCRIBE, PortSpec
from .fencing import NamespaceFence
from .params import param
from .ports import Ports
from .protocol_node import ROLES


class RecoveryNode(object):
    """Acts on the crash detector's verdicts about the peer replica.

    Backup whose primary failed: kill what is left of the primary's site, fence and promote
    this replica's After, bind the Protocol to the clients' topics through its rebind service,
    all three at once; then promote the Protocol once it stored every checkpointed reply
    (see aft_ftm.recovery for why this order is safe). Primary whose
    backup failed: kill what is left of the backup's site and tell After to stop
    checkpointing.

    Parameters:
        ~role (primary | backup): this replica's role at start.
        ~protocol (str, required): node name of this replica's Protocol.
        ~entry (str, default: the Protocol), ~entry_requests_port (default requests),
            ~entry_replies_port (default replies): the node and ports bound to the clients' topics
            (a SEC gate in front of the Protocol: sec_gate, requests_in, replies_out).
        ~promote (list of node names, default [after]): the nodes fenced and promoted, in order, before
            the Protocol (each one's SetRole last_seq is passed to the next): [before, after] for PBR and
            [before, after] for LFR.
        ~client_requests, ~client_replies (str, required for a backup): the Proxies' topics.
        ~peer_namespace (str, required): namespace of the peer site's nodes.
        ~service_timeout (float, 2 s): limit on each service call of a recovery.
        ~learn_period (float, 2 s): how often the pids of the peer's nodes are learned (for fail-silence).
    Subscribes:
        failures (aft_msgs/Failure), port ``failures``: from this site's crash detector.
    Publishes:
        ~events (std_msgs/String, latched): one JSON record per recovery (steps, durations).
    Services:
        ~rebind (aft_msgs/Rebind)
        ~set_promote (aft_msgs/SetNodes): replace the list of nodes to promote (an adaptation
            replaced Before or After); refused, changing nothing, unless each new node answers a
            SetRole for this replica's current role.
    """

    def __init__(self):
        self.role = ROLES[param('role', lambda n, v: config.one_of(n, v, ('primary', 'backup')), 'backup')]
        self.protocol = rospy.resolve_name(param('protocol', config.non_empty_str, required=True))
        self.entry = rospy.resolve_name(param('entry', config.non_empty_str, self.protocol))
        self.entry_requests = param('entry_requests_port', config.non_empty_str, 'requests')
        self.entry_replies = param('entry_replies_port', config.non_empty_str, 'replies')
        promote = param('promote', lambda n, v: v, ['after'])
        if not isinstance(promote, list) or not promote or not all(isinstance(x, str) and x for x in promote):
            raise config.ConfigError('parameter %s must be a non-empty list of node names, got %r'
                                     % (rospy.resolve_name('~promote'), promote))
        self.promote = [rospy.resolve_name(n) for n in promote]
        self.peer_ns = rospy.resolve_name(param('peer_namespace', config.non_empty_str, required=True))
        required = self.role == Role.BACKUP
        self.client_requests = param('client_requests', config.non_empty_str, required=required)
        self.client_replies = param('client_replies', config.non_empty_str, required=required)
        self.timeout = param('service_timeout', config.positive_float, 2.0)
        self.learn_period = param('learn_period', config.positive_float, 2.0)
        self.lock = threading.Lock()
        self.recovered = False
        self.last_seq = None   # set by PROMOTE_AFTER: the last checkpoint the promoted After holds

    def setup(self, timeout):
        names = [n + '/set_role' for n in self.promote] + (
            [self.protocol + '/set_role', self.entry + '/rebind'] if self.role == Role.BACKUP else [])
        for name in names:
            try:
                rospy.wait_for_service(name, timeout)
            except rospy.ROSException:
                rospy.logerr('%s: service %s not available within %.1f s', rospy.get_name(), name, timeout)
                return False
        # Persistent connections, opened now by no-op calls, so that a failover pays no connection set-up.
        self.set_role_nodes = [rospy.ServiceProxy(n + '/set_role', SetRole, persistent=True) for n in self.promote]
        self.set_role_protocol = rospy.ServiceProxy(self.protocol + '/set_role', SetRole, persistent=True)
        self.rebind_entry = rospy.ServiceProxy(self.entry + '/rebind', Rebind, persistent=True)
        try:
            for set_role in self.set_role_nodes:
                set_role(role=self.role.value)
            if self.role == Role.BACKUP:
                self.set_role_protocol(role=self.role.value, last_seq=0)
                bound = self.rebind_entry(port=self.entry_replies, topic=self.client_replies,
                                             direction=RebindRequest.PUBLISH, activate=True)
                if not bound.success:
                    rospy.logerr('%s: cannot bind the Protocol replies to %s: %s', rospy.get_name(),
                                 self.client_replies, bound.message)
                    return False
        except (rospy.ServiceException, rospy.ROSException) as e:
            rospy.logerr('%s: cannot reach this replica\'s nodes: %s', rospy.get_name(), e)
            return False
        self.fence = NamespaceFence(self.peer_ns, rospy.get_name())
        threading.Thread(target=self._learn_peer, name='learn-peer', daemon=True).start()
        self.events = rospy.Publisher('~events', String, queue_size=10, latch=True)
        self.ports = Ports([PortSpec('failures', SUBSCRIBE, 'aft_msgs/Failure')], {'failures': self._on_failure})
        self.ports.bind('failures')
        self.ports.advertise_service()
        rospy.Service('~set_promote', SetNodes, self._on_set_promote)
        return True

    def _on_set_promote(self, req):
        names = [rospy.resolve_name(n) for n in req.nodes]
        if not names or not all(req.nodes):
            return SetNodesResponse(success=False, message='give a non-empty list of node names',
                                    previous=self.promote)
        proxies = []
        with self.lock:   # no recovery runs while the list changes
            for name in names:
                try:
                    rospy.wait_for_service(name + '/set_role', self.timeout)
                    proxy = rospy.ServiceProxy(name + '/set_role', SetRole, persistent=True)
                    answer = proxy(role=self.role.value)
                except (rospy.ServiceException, rospy.ROSException) as e:
                    return SetNodesResponse(success=False, previous=self.promote,
                                            message='%s/set_role cannot be called: %s' % (name, e))
                if not answer.success:
                    return SetNodesResponse(success=False, previous=self.promote,
                                            message='%s refused role %s: %s' % (name, self.role.name, answer.message))
                proxies.append(proxy)
            previous, self.promote, self.set_role_nodes = self.promote, names, proxies
        rospy.loginfo('%s: nodes to promote are now %s (were %s)', rospy.get_name(), names, previous)
        return SetNodesResponse(success=True, message='promote %s' % ', '.join(names), previous=previous)

    def _set_role(self, index, **request):
        """Call set_role of promote node index; reconnect once if the persistent connection broke."""
        try:
            return self.set_role_nodes[index](**request)
        except (rospy.ServiceException, rospy.ROSException):
            self.set_role_nodes[index] = rospy.ServiceProxy(self.promote[index] + '/set_role', SetRole,
                                                            persistent=True)
            return self.set_role_nodes[index](**request)

    def _on_failure(self, failure):
        with self.lock:
            if self.recovered:
                return
            self.recovered = True
            record = {'failed_site': failure.site, 'reason': failure.reason, 'silence': failure.silence,
                      'role_before': self.role.name, 'steps': [], 'ok': True,
                      'detected_wall': failure.detected.to_sec()}
            start = self._start = time.monotonic()
            for wave in plan(self.role):
                threads = [threading.Thread(target=self._run_step, args=(step, failure, record)) for step in wave]
                for thread in threads:
                    thread.start()
                for thread in threads:
                    thread.join()
            record['seconds'] = time.monotonic() - start
            record['done_wall'] = time.time()
            self.role = role_after(self.role)
            record['role_after'] = self.role.name
        rospy.logwarn('%s: recovered from the failure of %s in %.1f ms: %s', rospy.get_name(), failure.site,
                      record['seconds'] * 1e3, ', '.join('%s%s' % (s['step'], '' if s['ok'] else ' FAILED')
                                                          for s in record['steps']))
        self.events.publish(String(data=json.dumps(record)))
        threading.Thread(target=self._clean_master, daemon=True).start()

    def _run_step(self, step, failure, record):
        t0 = time.monotonic()
        try:
            detail = self._do(step, failure)
            ok = True
        except Exception as e:   # a failed step is reported, and the next ones still run
            detail, ok = str(e), False
            record['ok'] = False
            rospy.logerr('%s: recovery step %s failed: %s', rospy.get_name(), step.name, e)
        record['steps'].append({'step': step.name, 'ok': ok, 'detail': detail,
                                'start': t0 - self._start, 'seconds': time.monotonic() - t0})

    def _do(self, step, failure):
        if step == Step.FAIL_SILENCE:
            return self._fail_silence(failure)
        if step == Step.PROMOTE_AFTER:
            last_seq = 0
            for index, name in enumerate(self.promote):
                result = self._set_role(index, role=Role.ALONE.value, last_seq=last_seq)
                if not result.success:
                    raise RuntimeError('%s refused: %s' % (name, result.message))
                last_seq = result.last_seq
            self.last_seq = last_seq
            return 'last checkpoint %d' % last_seq
        if step == Step.PROMOTE_PROTOCOL:
            if self.last_seq is None:
                # Never a Protocol serving clients without its After fenced against the old primary.
                raise RuntimeError('not promoted: the After was not promoted (see PROMOTE_AFTER)')
            result = self.set_role_protocol(role=Role.ALONE.value, last_seq=self.last_seq)
            if not result.success:
                raise RuntimeError('Protocol refused: %s' % result.message)
            return result.message
        if step == Step.BIND_CLIENT:
            # The replies port was bound to the clients' topic at set-up (checked there): its
            # publisher is already connected, so only the requests port is bound now.
            result = self.rebind_entry(port=self.entry_requests, topic=self.client_requests,
                                       direction=RebindRequest.SUBSCRIBE, activate=True)
            if not result.success:
                raise RuntimeError('rebind of requests refused: %s' % result.message)
            return result.message
        if step == Step.AFTER_ALONE:
            for index, name in enumerate(self.promote):
                result = self._set_role(index, role=Role.ALONE.value)
                if not result.success:
                    raise RuntimeError('%s refused: %s' % (name, result.message))
            return 'going on alone'
        raise ValueError(step)

    def _learn_peer(self):
        while not rospy.is_shutdown() and not self.recovered:
            try:
                self.fence.learn()
            except Exception as e:   # the master is unreachable for a while: try again later
                rospy.logwarn_throttle(30, '%s: cannot learn the nodes of %s: %s' % (rospy.get_name(), self.peer_ns, e))
            rospy.sleep(self.learn_period)

    def _fail_silence(self, failure):
        """Kill what is left of the failed site: its launcher's whole process tree when the heartbeat
        names one on this host, and every node of its name space whose pid was learned."""
        done = []
        if failure.pid > 0 and failure.host == this_host():
            done.append(self._power_off_launcher(failure))
        killed = self.fence.kill()
        done.append('%d nodes of %s killed by pid' % (len(killed), self.peer_ns))
        return '; '.join(done)

    def _power_off_launcher(self, failure):
        try:
            created = psutil.Process(failure.pid).create_time()
        except psutil.NoSuchProcess:
            return 'launcher of %s (pid %d) already gone' % (failure.site, failure.pid)
        if not same_process(created, failure.detected.to_sec() - failure.silence):
            return 'pid %d now belongs to another process: not killed' % failure.pid
        if os.getpid() in [p.pid for p in process_tree(failure.pid)]:
            return 'launcher %d also runs this replica: only the name space is killed' % failure.pid
        return '%d processes of the launcher of %s killed' % (power_off(failure.pid), failure.site)

    def _clean_master(self):
        """Ask the failed site's remaining nodes to shut down, and unregister the dead ones."""
        try:
            count = self.fence.shut_down_the_rest()
            rospy.loginfo('%s: master cleaned of %d nodes of %s', rospy.get_name(), count, self.peer_ns)
        except Exception as e:   # best effort: the failover is already done
            rospy.logwarn('%s: could not clean the master of %s: %s', rospy.get_name(), self.peer_ns, e)
