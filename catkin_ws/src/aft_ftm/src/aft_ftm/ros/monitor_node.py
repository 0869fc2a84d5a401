"""The Monitoring Engine: publishes the change model (F, A, R) and adapts the FTM when the
running composition is no longer consistent with it (paper section 4.2)."""
import json
import queue
import threading
import time

import rospy
from aft_msgs.msg import Alarm, Application, Configuration, Heartbeat
from std_msgs.msg import Float64, String

from .. import change_model, config, mechanisms
from ..adaptation import ScriptError
from ..change_model import Application as AppModel
from ..errors import ConfigError
from ..monitor import ForgedAlarm, MonitorCore, transition
from .alarms import alarm
from .params import param
from .witness_client import DEFAULT_WITNESS, configuration_topic, from_witness_only


def _names(name, value):
    if isinstance(value, str):
        value = [v.strip() for v in value.split(',') if v.strip()]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError('parameter %s must be a list of names, got %r' % (name, value))
    return value


def _script_args(name, value):
    """{script: [name:=value, ...]}: the arguments the monitor gives each shipped script (a service's
    own names: server:=, state_manager:=, assertions), each checked now."""
    from ..adaptation import ScriptError, parse_overrides
    if not isinstance(value, dict):
        raise ConfigError('parameter %s must map script names to lists of name:=value, got %r' % (name, value))
    for script, items in value.items():
        items = config.name_list('%s/%s' % (name, script), items)
        try:
            parse_overrides(items)
        except ScriptError as e:
            raise ConfigError('parameter %s/%s: %s' % (name, script, e))
        value[script] = items
    return value


class MonitorNode(object):
    """Keeps (F, A, R) up to date, selects the cheapest consistent mechanism from Table I, and when
    the running one is no longer consistent, runs the matching adaptation script and logs why.

    Parameters:
        ~faults (list, default [crash]): F as declared by the operator (fault kinds of aft_ftm.mechanisms).
        ~deterministic, ~state_access (bool, default true): A as declared at start.
        ~sites (list, default [master, slave]): the replica sites, primary first.
        ~witness (str, default /aft/witness/request; none: no witness): the service of the sites'
            witness, whose configurations (its node's ~configuration) say a site re-joined. It and
            ~ftm_ns are given to every adaptation script it runs that takes them (witness:=, ftm_ns:=),
            so that the nodes they start follow that witness on those topics.
        ~running (str, default pbr): the composition running at start, e.g. pbr or pbr+tr.
        ~lost_after (float, 2 s): a site heard, then silent this long while the monitor ran, is lost for
            good (R: CPUs); a site never heard waits for its first beat; a gap between the monitor's own
            ticks of more than lost_after / 2 (a stall) is not counted as the sites' silence.
        ~bandwidth_high, ~bandwidth_low (float, 1e6 and 1e4 B/s): what a link must carry for
            mechanisms needing high / low bandwidth (Table I).
        ~mode (prepared | paper, default prepared): the order adaptations run in.
        ~script_args (dict, default {}): arguments given to each shipped script, before the monitor's
            own, e.g. {compose: [server:=plan, state_manager:=planner], switch: [state_manager:=planner]}.
        ~alarms_from (list of absolute names, default [/proxy, /sec_gate]): the nodes or namespaces
            outside the sites whose alarms count (the service's Proxies, its clients' SEC gates). The
            alarms of every node of the sites (/SITE/...) count; any other node's (another service's
            on the same ROS master: /aft/alarms is shared) are logged once per node and change nothing.
        ~period (float, 0.1 s): how often the model is checked.
        ~retry_hold (float, 2 s), ~retry_hold_max (float, 120 s): an adaptation that failed on a model is
            tried again on that model (it came back: a bandwidth flapping across a threshold) only after
            a hold that doubles with each failure there, up to ~retry_hold_max; a success forgets them.
    Subscribes:
        <ftm_ns>/heartbeat/<site> (aft_msgs/Heartbeat): R, the sites alive.
        alarms (aft_msgs/Alarm): faults observed by the mechanisms extend F; an alarm whose source is
            not the node that sent it (the connection's caller id) is refused, F unchanged.
        ~declare_faults (std_msgs/String, comma-separated kinds): the operator changes F.
        ~application (aft_msgs/Application): the application declares A (a new version).
        ~bandwidth (std_msgs/Float64, bytes/s): available bandwidth between the sites, from a link monitor.
    Publishes:
        ~model (std_msgs/String, JSON, latched): F, A, R, the running composition, the sites alive and
            those never heard, the selection over every composition (selection) and the one the monitor
            would adapt to: among those a shipped script reaches from the running one (reachable_selection).
        ~events (std_msgs/String, JSON, latched): each decision, adaptation report or failure.
        alarms (aft_msgs/Alarm, mechanism monitor): forged_alarm, for each alarm refused; adaptation_failed
            (refused or rolled back), rollback_failed (the report's state FAILED), adaptation_incomplete
            (it stands, with an alarm), for each adaptation; degraded (the running composition is
            inconsistent, and kept: no composition a shipped script reaches from it covers more of F)
            and no_mechanism_fits (none of them, the running one included, covers any of F or can run),
            once each time the running composition or the model (F, A, sites alive, bandwidth level)
            changes.
    """

    def __init__(self):
        faults = param('faults', _names, ['crash'])
        deterministic = param('deterministic', config.flag, True)
        state_access = param('state_access', config.flag, True)
        self.sites = param('sites', _names, ['master', 'slave'])
        running = tuple(param('running', config.non_empty_str, 'pbr').split('+'))
        lost_after = param('lost_after', config.positive_float, 2.0)
        high = param('bandwidth_high', config.positive_float, 1e6)
        low = param('bandwidth_low', config.positive_float, 1e4)
        self.mode = param('mode', config.choice('prepared', 'paper'), 'prepared')
        self.script_args = param('script_args', _script_args, {})
        self.period = param('period', config.positive_float, 0.1)
        self.ftm_ns = param('ftm_ns', config.non_empty_str, '/ftm')
        self.witness = param('witness', config.witness_service, DEFAULT_WITNESS)
        try:
            for name in running:
                mechanisms.mechanism(name)
            self.core = MonitorCore(faults, AppModel(deterministic, state_access), self.sites, running,
                                    time.monotonic(), lost_after, high, low,
                                    retry_hold=param('retry_hold', config.non_negative_float, 2.0),
                                    retry_hold_max=param('retry_hold_max', config.non_negative_float, 120.0),
                                    alarms_from=param('alarms_from', _names, ['/proxy', '/sec_gate']),
                                    follows_witness=bool(self.witness))
        except ConfigError as e:
            raise ConfigError('%s: %s' % (rospy.get_name(), e))
        self.lock = threading.Lock()
        self.suffix = ''
        self.work = queue.Queue()
        self.engine = None
        self.forged = 0   # alarms refused: their source is not the node that sent them

    def setup(self, timeout):
        from .adaptation_engine import Engine
        self.engine = Engine(log=lambda text: rospy.loginfo('%s: %s', rospy.get_name(), text))
        self.model_pub = rospy.Publisher('~model', String, queue_size=1, latch=True)
        self.events = rospy.Publisher('~events', String, queue_size=100, latch=True)
        self.alarms = rospy.Publisher('alarms', Alarm, queue_size=100)
        for site in self.sites:
            rospy.Subscriber('%s/heartbeat/%s' % (self.ftm_ns, site), Heartbeat, self._on_heartbeat, site)
        rospy.Subscriber('alarms', Alarm, self._on_alarm)
        rospy.Subscriber('~declare_faults', String, self._on_faults)
        rospy.Subscriber('~application', Application, self._on_application)
        rospy.Subscriber('~bandwidth', Float64, self._on_bandwidth)
        if self.witness:
            rospy.Subscriber(configuration_topic(self.witness), Configuration, from_witness_only(
                self.witness, self._on_configuration,
                report=lambda detail: alarm(self, 'monitor', 'forged_configuration', detail)))
        threading.Thread(target=self._adapter, name='adapter', daemon=True).start()
        self.timer = rospy.Timer(rospy.Duration(self.period), self._tick)
        rospy.on_shutdown(self.engine.shutdown)   # what its adaptations put in place runs on
        return True

    # -- events -------------------------------------------------------------------------------
    def _on_heartbeat(self, _msg, site):
        with self.lock:
            self.core.heartbeat(site, time.monotonic())

    def _on_configuration(self, conf):
        """A lost site the witness admits again (it re-joined): R changes back."""
        if conf.primary in self.sites or conf.backup in self.sites:
            with self.lock:
                newest = self.core.witness_heard(time.monotonic(), conf.primary, conf.epoch)
            if not newest:   # an older configuration (a witness started again from an older record): a lost
                return       # site it names has not re-joined (review of session 48)
        for site in (conf.primary, conf.backup):
            if site in self.sites:
                with self.lock:
                    back = self.core.rejoined(site, time.monotonic())
                if back:
                    self._event({'event': 'site re-joined', 'site': site, 'epoch': conf.epoch})

    def _on_alarm(self, msg):
        sender = (getattr(msg, '_connection_header', None) or {}).get('callerid')
        try:
            with self.lock:
                fault = self.core.alarm(msg.mechanism, msg.kind, time.monotonic(), msg.source, sender)
        except ForgedAlarm as e:
            self.forged += 1
            detail = '%s: refused, F unchanged (%d so far)' % (e, self.forged)
            alarm(self, 'monitor', 'forged_alarm', detail)
            return
        if fault:
            rospy.logwarn('%s: %s alarm %s: F now includes %s', rospy.get_name(), msg.mechanism, msg.kind, fault)

    def _on_faults(self, msg):
        faults = [f.strip() for f in msg.data.split(',') if f.strip()]
        try:
            with self.lock:
                self.core.declare_faults(faults, time.monotonic())
        except ConfigError as e:
            rospy.logerr('%s: declaration refused, F unchanged: %s', rospy.get_name(), e)

    def _on_application(self, msg):
        with self.lock:
            self.core.declare_application(AppModel(msg.deterministic, msg.state_access), time.monotonic())
        rospy.logwarn('%s: the application declares deterministic=%s state_access=%s', rospy.get_name(),
                      msg.deterministic, msg.state_access)

    def _on_bandwidth(self, msg):
        try:
            with self.lock:
                self.core.bandwidth(msg.data, time.monotonic())
        except ConfigError as e:
            rospy.logerr('%s: bandwidth measurement refused: %s', rospy.get_name(), e)

    def publish(self, port, msg):
        """The ports interface of aft_ftm.ros.alarms.alarm: the node's one port is ``alarms``."""
        if port != 'alarms':
            raise ConfigError('the monitor publishes no port %r' % (port,))
        self.alarms.publish(msg)

    def _raise(self, alarms):
        """Publish the core's alarms (taken under the lock, published outside it)."""
        for a in alarms:
            alarm(self, 'monitor', a.kind, a.detail)

    # -- decisions ----------------------------------------------------------------------------
    def _tick(self, _event):
        with self.lock:
            decision = self.core.decide(time.monotonic())
            alarms = self.core.take_alarms()
            model = self.core.model()
            running = change_model.composition_name(self.core.running)
            alive = self.core.alive_sites()
            never_heard = [s for s in alive if self.core.last_heard[s] is None]
            reachable = self.core.selection()
        self.model_pub.publish(String(data=json.dumps({
            'model': model.to_dict(), 'running': running, 'alive_sites': alive, 'never_heard': never_heard,
            'selection': change_model.select(model, self.core.high, self.core.low).to_dict(),
            'reachable_selection': reachable.to_dict()}, sort_keys=True)))
        self._raise(alarms)
        if decision is not None:
            self.work.put((decision, alive))

    def _event(self, record):
        rospy.logwarn('%s: %s', rospy.get_name(), json.dumps(record, sort_keys=True))
        self.events.publish(String(data=json.dumps(record, sort_keys=True)))

    def _adapter(self):
        """Carries out decisions one at a time, off the ROS callback threads."""
        while not rospy.is_shutdown():
            try:
                decision, alive = self.work.get(timeout=0.5)
            except queue.Empty:
                continue
            try:
                self._carry_out(decision, alive)
            except Exception as e:   # this thread must live on: dead, the monitor never adapted again, unsaid
                rospy.logerr('%s: carrying out %s failed: %s: %s', rospy.get_name(), decision, type(e).__name__, e)
                with self.lock:
                    try:
                        self.core.adaptation_failed('%s: %s' % (type(e).__name__, e), time.monotonic())
                    except Exception:   # (not ADAPTING any more: nothing to end)
                        pass
                    alarms = self.core.take_alarms()
                self._raise(alarms)

    def _carry_out(self, decision, alive):
        """Run the decision's script; tell the core the outcome, publish the event and the alarms."""
        record = {'event': 'decision', 'decision': decision.to_dict()}
        report = {}
        try:
            if not decision.to:
                raise ConfigError('the selection keeps nothing (%s): the running mechanism is kept'
                                  % decision.selection.reason)
            move = transition(decision.from_, decision.to, alive, self.suffix)
            # The replicas' witness and topics' namespace, to a script that takes them (the nodes it starts
            # follow that witness, on those topics), then the operator's arguments for it, then the move's own.
            from .adapt_command import declared_args, load_script
            declared = declared_args(move.script)
            deployment = [a for a in ('witness:=%s' % (self.witness or 'none'), 'ftm_ns:=%s' % self.ftm_ns)
                          if a.split(':=')[0] in declared]
            move = move._replace(overrides=deployment + list(self.script_args.get(move.script, [])) + list(
                move.overrides))
            record['script'], record['args'] = move.script, move.overrides
            self._event(record)
            report = self.engine.run(load_script(move.script, move.overrides), self.mode)
            ok = report['ok']
            error = report['error']
            record = {'event': 'adapted' if ok else 'adaptation_failed', 'report': report}
        except (ConfigError, ScriptError) as e:
            ok, error = False, str(e)
            record = {'event': 'adaptation_failed', 'error': error, 'decision': decision.to_dict()}
        except Exception as e:   # never leave the monitor ADAPTING forever: report and go on
            ok, error = False, '%s: %s' % (type(e).__name__, e)
            record = {'event': 'adaptation_failed', 'error': error, 'decision': decision.to_dict()}
        with self.lock:
            if ok:
                self.core.adapted(decision.to, time.monotonic(), alarm=report.get('alarm') or '')
                self.suffix = move.suffix
            else:
                rollback_failed = report.get('state') == 'FAILED'
                if rollback_failed and report.get('alarm'):
                    error = report['alarm']   # the error, and what the rollback could not undo
                self.core.adaptation_failed(error, time.monotonic(), rollback_failed=rollback_failed)
            alarms = self.core.take_alarms()
        self._event(record)
        self._raise(alarms)
