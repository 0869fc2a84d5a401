"""An intruder on the ROS graph (issue 16): what any process that reaches the ROS master can try,
made into a tool that tests and scenarios run against a deployment. It reads the graph from the
master, as ROS 1 lets anyone, then
- publishes a default message of the right type on every topic somebody subscribes to, latched,
  and holds it for ``hold`` seconds (every subscriber is told of the new publisher and tries it);
- calls every service with a default request;
and reports what got through: the topics on which a subscriber connected, the services that
answered. Names the policy lists as plaintext (the application's open interface), this process's
own and the roscore's log node are skipped. Under mutual TLS nothing should get through."""
import time

import rosgraph
import roslib.message
import rospy
import rosservice


def sweep(permissions=None, hold=2.0, log=None):
    """Returns {'topics': [...tried], 'connected': [...], 'services': n tried, 'called': [...their names],
    'refused': n, 'unknown': [...services whose type could not be read], 'served': [...]}."""
    me = rospy.get_name()
    master = rosgraph.Master(me)
    _, subscribed, services = master.getSystemState()
    types = dict(master.getTopicTypes())
    open_name = permissions.plaintext if permissions is not None else (lambda name: name == '/rosout')
    forged = []
    for topic, nodes in sorted(subscribed):
        if open_name(topic) or topic not in types or nodes == [me]:
            continue
        kind = roslib.message.get_message_class(types[topic])
        if kind is None:
            continue
        publisher = rospy.Publisher(topic, kind, queue_size=10, latch=True)
        publisher.publish(kind())
        forged.append((topic, publisher))
    time.sleep(hold)
    report = {'topics': [t for t, _ in forged], 'connected': [t for t, p in forged if p.get_num_connections()],
              'services': 0, 'called': [], 'refused': 0, 'unknown': [], 'served': []}
    for _, publisher in forged:
        publisher.unregister()
    for name, providers in sorted(services):
        if open_name(name) or name.startswith(me + '/') or providers == ['/rosout']:
            continue
        report['services'] += 1
        report['called'].append(name)
        try:
            kind = rosservice.get_service_class_by_name(name)
        except Exception:   # gone, or its type not given to this caller
            report['unknown'].append(name)
            continue
        try:
            rospy.ServiceProxy(name, kind)(kind._request_class())
            report['served'].append(name)
        except rospy.ServiceException as e:
            if 'responded with an error' in str(e):   # its handler ran (and refused the default request)
                report['served'].append(name)
            else:
                report['refused'] += 1
        except Exception:   # the connection refused (TLS, policy), the node gone
            report['refused'] += 1
    return report
