"""Where an alarm's detail is logged (aft_ftm.ros.alarms.log_alarm): no ROS master."""
from aft_ftm.ros import alarms

DETAIL = 'amount 5000 above the limit 1000 (request /proxy/7 from /bank_client)'


def capture(monkeypatch):
    said = {'rosout': [], 'local': []}
    monkeypatch.setattr(alarms.rospy, 'logwarn', lambda text, *args: said['rosout'].append(text % args))
    monkeypatch.setattr(alarms.rospy, 'get_name', lambda: '/master/before')
    monkeypatch.setattr(alarms.LOCAL, 'warning', lambda text, *args: said['local'].append(text % args))
    return said


def test_under_tls_the_detail_stays_off_rosout_which_is_in_clear(monkeypatch):
    """Issue 16: /rosout is in clear (ROS's own node, without TLS), and an assertion's alarm names the
    request's values: under TLS they went to any process on the graph. Now /rosout gets the alarm's
    mechanism and kind; the detail goes on /aft/alarms (TLS) and into the node's own log file."""
    said = capture(monkeypatch)
    alarms.log_alarm('ad', 'assertion_violated', DETAIL, tls=True)
    assert len(said['rosout']) == 1 and '5000' not in said['rosout'][0]
    assert 'ad assertion_violated' in said['rosout'][0] and '/aft/alarms' in said['rosout'][0]
    assert said['local'] == ['/master/before: ad assertion_violated: %s' % DETAIL]


def test_without_tls_the_alarm_is_logged_whole_on_rosout_as_before(monkeypatch):
    said = capture(monkeypatch)
    alarms.log_alarm('ad', 'assertion_violated', DETAIL, tls=False)
    assert said == {'rosout': ['/master/before: ad assertion_violated: %s' % DETAIL], 'local': []}


def test_the_local_logger_is_one_rospy_keeps_to_the_node_s_own_file():
    """rospy publishes on /rosout what its 'rosout' logger logs; the 'rospy.*' loggers go to the
    node's log file (its python_logging.conf)."""
    assert alarms.LOCAL.name.startswith('rospy.') and not alarms.LOCAL.name.startswith('rosout')


def test_whether_tls_is_installed_is_asked_when_not_told(monkeypatch):
    from aft_ftm.ros import tls_transport
    said = capture(monkeypatch)
    monkeypatch.setattr(tls_transport, '_STATE', {'party': 'master'})
    alarms.log_alarm('ad', 'assertion_violated', DETAIL)
    assert said['local'] and '5000' not in said['rosout'][0]
