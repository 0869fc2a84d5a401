"""rosrun aft_ftm rejoin, with the witness faked: no ROS master."""
import types

from aft_ftm.ros import rejoin_command


def test_a_launch_asked_for_the_witnesss_primary_is_refused_as_a_failure_not_an_exit_0(monkeypatch, capsys):
    """Review of the witness (session 33): right after the primary failed (before its peer's verdict),
    `rejoin SITE --launch ...` printed "nothing to re-join", exited 0 and started nothing."""
    monkeypatch.setattr(rejoin_command.rospy, 'wait_for_service', lambda service, timeout: None)
    monkeypatch.setattr(rejoin_command, 'status',
                        lambda service: types.SimpleNamespace(epoch=7, primary='master', backup='slave'))
    started = []
    monkeypatch.setattr(rejoin_command.subprocess, 'Popen', lambda *a, **k: started.append(a))
    assert rejoin_command.main(['master', '--launch', 'roslaunch x y.launch']) == 1
    assert started == [] and 'not launched' in capsys.readouterr().err
    assert rejoin_command.main(['master']) == 0     # without --launch: nothing to re-join, as before
