"""A replica's WitnessClient, its configuration callback driven by hand (rospy's Subscriber faked). No ROS."""
import threading
import types

from aft_ftm.ros import witness_client


def test_every_older_configuration_is_told_to_the_witness_not_once_per_epoch_number(monkeypatch):
    """Review of the witness (session 33): a site told a witness behind only once per epoch number. A
    witness restarted twice without its record publishes epoch 0 both times: the second time nobody
    told it, and it handed out the first primary's role again."""
    heard = {}
    monkeypatch.setattr(witness_client.rospy, 'Subscriber',
                        lambda topic, kind, callback, **kw: heard.setdefault('callback', callback))
    told = []
    client = witness_client.WitnessClient.__new__(witness_client.WitnessClient)
    client.known, client.seen, client._seen_lock = 0, {}, threading.Lock()
    client.service = witness_client.DEFAULT_WITNESS
    client._tell_behind = lambda epoch: told.append(epoch)
    monkeypatch.setattr(witness_client.threading, 'Thread',
                        lambda target, args, **kw: types.SimpleNamespace(start=lambda: target(*args)))
    client.subscribe(lambda conf: None)
    conf = lambda epoch: types.SimpleNamespace(epoch=epoch, primary='slave' if epoch else 'master', backup='')  # noqa
    heard['callback'](conf(5))
    heard['callback'](conf(0))          # the witness restarted without its record
    heard['callback'](conf(0))          # ... and again
    assert told == [0, 0] and client.known == 5


def test_a_registration_whose_answer_was_lost_is_asked_again_within_the_set_up_time(monkeypatch):
    """Review of the witness (session 33): a REGISTER past its call limit (a slow disk at the witness)
    failed the set-up at once; granted meanwhile, it left the first primary's role to an incarnation
    that had stopped, and nobody could ever serve. It is asked again; the same incarnation is granted."""
    from aft_ftm.ros import recovery_node
    from aft_ftm.witness import Grant
    answers = [witness_client.WitnessUnreachable('witness /aft/witness/request: timed out after 1.0 s'),
               Grant(True, 'slave is the backup of epoch 2', 2, 'master', 'slave')]

    def request(op, claim=False):
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer
    node = recovery_node.RecoveryNode.__new__(recovery_node.RecoveryNode)
    node.witness = types.SimpleNamespace(request=request)
    node.claim, node.site, node.role = False, 'slave', recovery_node.Role.BACKUP
    events = []
    node._event = events.append
    monkeypatch.setattr(recovery_node.time, 'sleep', lambda s: None)
    assert node._register(timeout=5.0) is True
    assert answers == [] and node.epoch == 2 and events[0]['epoch'] == 2


def test_an_lfr_leader_whose_admit_went_unanswered_voids_it_before_it_serves_alone(monkeypatch):
    """Review of the witness (session 33): the leader gave up an unanswered ADMIT and served alone; the
    witness carried it out later, after the leader had lost power, and promoted the follower, which
    held none of the replies released meanwhile. The leader now has an EXCLUDE granted first (a new
    epoch: the ADMIT of the old one is refused), asking while its Protocol stays held."""
    import threading
    from aft_ftm.ros import lfr_nodes
    leader = lfr_nodes.LfrAfterNode.__new__(lfr_nodes.LfrAfterNode)
    leader.lock, leader.site, leader.state_timeout = threading.RLock(), 'master', 5.0
    leader.core = types.SimpleNamespace(epoch=3)
    answers = [None, types.SimpleNamespace(epoch=5, message='master is already alone, in epoch 5 now')]
    told, held = [], []
    leader.side = types.SimpleNamespace(exclusion=lambda deposed: answers.pop(0),
                                        hold_protocol=lambda lease: held.append(lease),   # None: still held
                                        tell=lambda kind, detail, key=None: told.append((kind, detail)))
    monkeypatch.setattr(lfr_nodes.time, 'sleep', lambda s: None)
    leader._void_admit('slave')
    assert answers == [] and leader.core.epoch == 5 and held == [10.0]
    assert told[0][0] == 'join_failed' and 'voids it' in told[0][1]
    # the witness never answers: bounded, and said
    clock = iter(range(0, 100, 3))
    monkeypatch.setattr(lfr_nodes.time, 'monotonic', lambda: next(clock))
    leader.side.exclusion = lambda deposed: None
    told.clear()
    leader._void_admit('slave')
    assert told and told[-1][0] == 'admit_unsettled'


def test_one_epoch_naming_two_configurations_makes_the_site_tell_the_witness_it_is_behind(monkeypatch):
    """Review of the witness (session 33): a witness restored from an older record granted epoch 3 a
    second time, to the other site; configurations of an equal epoch were ignored, and both sites served
    in epoch 3. Two contents for one epoch now make the site tell the witness it is behind that epoch."""
    heard = {}
    monkeypatch.setattr(witness_client.rospy, 'Subscriber',
                        lambda topic, kind, callback, **kw: heard.setdefault('callback', callback))
    monkeypatch.setattr(witness_client.threading, 'Thread',
                        lambda target, args, **kw: types.SimpleNamespace(start=lambda: target(*args)))
    told = []
    client = witness_client.WitnessClient.__new__(witness_client.WitnessClient)
    client.known, client.seen, client._seen_lock = 0, {}, threading.Lock()
    client.service = witness_client.DEFAULT_WITNESS
    client._tell_behind = lambda epoch: told.append((epoch, client.known))
    client.subscribe(lambda conf: None)
    conf = lambda epoch, primary, backup='': types.SimpleNamespace(epoch=epoch, primary=primary, backup=backup)  # noqa
    heard['callback'](conf(3, 'slave'))          # slave promoted: epoch 3
    heard['callback'](conf(3, 'slave'))          # the same again (a latched copy): nothing
    assert told == []
    heard['callback'](conf(3, 'master'))         # epoch 3 granted again, to master
    assert told == [(3, 4)]                      # told, saying epoch 4: it grants nothing more


def test_an_lfr_follower_is_not_admitted_if_the_protocol_resumed_while_the_witness_answered(monkeypatch):
    """Review of session 36: the Protocol was checked held once, before the witness's ADMIT; its
    answer and Before's can take seconds (the leader's After stopped), the Protocol's lease ran out
    meanwhile and it ran requests, and the follower was admitted without them, silently."""
    import threading
    from aft_ftm.ros import lfr_nodes
    from aft_ftm.lfr import Role
    for resumed in (False, True):
        leader = lfr_nodes.LfrAfterNode.__new__(lfr_nodes.LfrAfterNode)
        leader.lock, leader.site, leader.name = threading.RLock(), 'master', '/master/after'
        leader.state_timeout, leader.ack_timeout, leader.chunk_bytes, leader.transfer_window = 5.0, 1.0, 1 << 20, 4
        leader.state_calls = types.SimpleNamespace(call=lambda f, t: types.SimpleNamespace(state=b'state'))
        leader.get_state = None
        holds = [None, None, 'its lease ran out: it resumed by itself' if resumed else None]
        told, excluded, admitted, forwarded = [], [], [], []
        leader.side = types.SimpleNamespace(
            hold_protocol=lambda lease: holds.pop(0), joiner_unheard=lambda site: '',
            ask=lambda op, **kw: types.SimpleNamespace(granted=True, epoch=7, primary='master', message=''),
            tell=lambda kind, detail, key=None: told.append((kind, detail)), told=set())
        transfer = types.SimpleNamespace(seq=4, cache=[], acknowledged_s=0.1)
        leader.core = types.SimpleNamespace(epoch=6, start_transfer=lambda site, t0: transfer,
                                            end_transfer=lambda: None,
                                            admitted=lambda *a: admitted.append(a))
        leader._send_transfer = lambda out, transfer: True
        leader._forwarding = lambda role, epoch, seq=0: forwarded.append((role, epoch)) or True
        leader._exclude = lambda why: excluded.append(why)
        leader.events = types.SimpleNamespace(publish=lambda msg: None)
        leader._join(types.SimpleNamespace(site='slave', after='/slave/after', incarnation='i2'))
        assert forwarded == [(Role.PRIMARY, 7)] and holds == []
        if resumed:
            assert admitted == [] and excluded and 'lacks them' in excluded[0], (admitted, excluded)
            assert told and told[-1][0] == 'join_failed', told
        else:
            assert len(admitted) == 1 and excluded == [], (admitted, excluded)


def test_a_configuration_from_another_node_than_the_witness_is_refused_and_reported_once():
    """Review of session 41: anyone could publish on a witness's configuration topic; one forged
    configuration with a higher epoch deposed the serving primary and made Recovery claim it as its
    known epoch, after which the witness granted nothing. Only the witness's own node is heard."""
    import types
    from aft_ftm.ros.witness_client import from_witness_only, witness_node
    assert witness_node('/bank/witness/request') == '/bank/witness' and witness_node('/request') == '/'
    heard, reports = [], []
    guarded = from_witness_only('/bank/witness/request', heard.append, reports.append)

    def conf(sender, epoch):
        msg = types.SimpleNamespace(epoch=epoch, primary='slave', backup='', _connection_header={'callerid': sender})
        if sender is None:
            del msg._connection_header
        return msg
    for sender, epoch in (('/bank/witness', 3), ('/bank_client_x', 99), ('/bank_client_x', 100), ('/aft/witness', 7),
                          ('/bank/witness/x', 8), (None, 4)):
        guarded(conf(sender, epoch))
    assert [c.epoch for c in heard] == [3, 4]
    assert len(reports) == 3 and 'came from /bank_client_x, not from the witness /bank/witness' in reports[0]
