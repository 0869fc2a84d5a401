"""The car's commandManager takes controllerPid's commands only from the board the watchdog names.

Both boards' Afters publish fresh commands on /tjp/pid_command (two processes named as the Afters,
board_a's accelerating, board_b's braking), as when a deposed board nobody could power off resumes.
A stand-in for the watchdog publishes its latched word (aft_msgs/PrimaryBoard) at moments drawn from
a seed. Checked on what reaches the car (/car/command): before any word, only ~sources (board_a);
after the word naming board_b, only board_b, within the time the word takes; a word of a term
already passed, the same term naming another board, naming no node, from another watchdog run
naming another board, or from a node that is not ~watchdog changes nothing and is alarmed
(primary_ignored, primary_disputed); the word in force heard again is not; the refused board is
alarmed (foreign_command) once per word (exactly once while the word stands); a commandManager started again while the word
stands never takes board_a's commands, though its configuration names board_a (it waits for the
latched word; on an idle machine the word also comes before board_a's first command without the
wait, which matters on a loaded one: this phase checks the property, it does not isolate the wait).
Runs with a master of its own; every process carries the test's AFT_TEST_TAG and is killed at the
end, pass or fail. AFT_SEED replays a run."""
from leftovers import run_seeded

SCRIPT = r'''
import random, subprocess, sys, tempfile, time
import rospy
from aft_msgs.msg import Alarm, CarCommand, PrimaryBoard
from aft_ftm.ros.graph import start_master
from aft_ftm.sites import wait_until

seed = int(sys.argv[1])
rng = random.Random(seed)
A, B = '/board_a/cycle_after', '/board_b/cycle_after'
log_dir = tempfile.mkdtemp(prefix='aft_command_sources_')
core = start_master(log_dir)
BOARD = r"""
import sys, rospy
from aft_msgs.msg import CarCommand
rospy.init_node(sys.argv[1].rsplit('/', 1)[1])
out = rospy.Publisher('/tjp/pid_command', CarCommand, queue_size=10)
rate = rospy.Rate(20)
while not rospy.is_shutdown():
    out.publish(CarCommand(stamp=rospy.Time.now(), accel=float(sys.argv[2]), source=sys.argv[1]))
    rate.sleep()
"""
procs = []


def start(argv, name):
    proc = subprocess.Popen(argv, stdout=open('%s/%s.out' % (log_dir, name), 'w'), stderr=subprocess.STDOUT)
    procs.append(proc)
    return proc


def command_manager():
    return start(['rosrun', 'tjp_sim', 'command_manager', '__name:=command_manager', '__ns:=/tjp',
                  '_sources:=[%s]' % A, '_watchdog:=/watchdog', 'command:=/car/command', 'alarms:=/aft/alarms'],
                 'command_manager')


FORGER = r"""
import sys, time, rospy
from aft_msgs.msg import PrimaryBoard
rospy.init_node('forger')
out = rospy.Publisher('/tjp/primary', PrimaryBoard, queue_size=1, latch=True)
out.publish(PrimaryBoard(stamp=rospy.Time.now(), board='board_a', nodes=[sys.argv[1]], term=99,
                         incarnation=sys.argv[2]))
time.sleep(3)
"""


def board(name, accel):
    return start([sys.executable, '-c', BOARD, name, str(accel), '__name:=%s' % name.rsplit('/', 1)[1],
                  '__ns:=%s' % name.rsplit('/', 1)[0]], name.strip('/').replace('/', '_'))


try:
    rospy.init_node('watchdog', disable_signals=True)   # the stand-in for the watchdog
    car, alarms = [], []
    rospy.Subscriber('/car/command', CarCommand, lambda m: car.append((time.monotonic(), m.source, m.accel, m.mode)))
    rospy.Subscriber('/aft/alarms', Alarm, lambda m: alarms.append((time.monotonic(), m.source, m.kind, m.detail)))
    word = rospy.Publisher('/tjp/primary', PrimaryBoard, queue_size=10, latch=True)
    manager = command_manager()
    boards = [board(A, 1.0), board(B, -1.0)]
    rng.shuffle(boards)

    def driven(since):
        return sorted({s for t, s, _, mode in car if t >= since and mode in (0, 3) and s != '/tjp/command_manager'})

    def kinds(kind, since):
        return [a for a in alarms if a[2] == kind and a[0] >= since]

    if not wait_until(lambda: driven(0) == [A] and kinds('foreign_command', 0), 60.0, 0.05):
        sys.exit('seed %d: before any word, the car was not driven by board_a alone with board_b refused: %s; '
                 'alarms %s; %s' % (seed, driven(0), alarms[-4:],
                                    open(log_dir + '/command_manager.out').read()[-2000:]))
    t0 = time.monotonic()
    time.sleep(rng.uniform(0.3, 1.0))
    if driven(t0) != [A] or len(kinds('foreign_command', 0)) != 1 or B not in kinds('foreign_command', 0)[0][3]:
        sys.exit('seed %d: before any word: driven by %s; foreign alarms (one for board_b expected) %s'
                 % (seed, driven(t0), kinds('foreign_command', 0)))
    print('seed %d: before any word the car was driven by board_a only, board_b refused (foreign_command)' % seed,
          flush=True)

    # The watchdog names board_b the primary (term 2).
    said = time.monotonic()
    word.publish(PrimaryBoard(stamp=rospy.Time.now(), board='board_b', nodes=[B], term=2, incarnation='w1'))
    if not wait_until(lambda: driven(said)[-1:] == [B] if driven(said) else False, 5.0, 0.01):
        sys.exit('seed %d: board_b never drove after the word naming it: %s' % (seed, car[-4:]))
    switched = min(t for t, s, _, _ in car if t >= said and s == B)
    settle = switched + 0.3
    time.sleep(rng.uniform(0.5, 1.0))
    refused_a = [a for a in kinds('foreign_command', said) if A in a[3].split(', not by')[0]]
    if driven(settle) != [B] or len(refused_a) != 1:
        sys.exit('seed %d: after the word naming board_b: driven by %s; foreign alarms since (one for board_a '
                 'expected) %s' % (seed, driven(settle), kinds('foreign_command', said)))
    print('seed %d: board_b drove %.0f ms after the word naming it, board_a refused from then on'
          % (seed, (switched - said) * 1e3), flush=True)

    # Words that must change nothing, in an order drawn from the seed: a passed term, the same term naming
    # the other board, none named, another watchdog run naming the other board (a watchdog started again
    # starts from its configured primary), a word from a node that is not the watchdog.
    stale = [PrimaryBoard(stamp=rospy.Time.now(), board='board_a', nodes=[A], term=rng.choice([1, 2]),
                          incarnation='w1'),
             PrimaryBoard(),
             PrimaryBoard(stamp=rospy.Time.now(), board='board_a', nodes=[A], term=1, incarnation='w2'),
             'forger']
    rng.shuffle(stale)
    before = time.monotonic()
    for msg in stale:
        if msg == 'forger':
            start([sys.executable, '-c', FORGER, A, rng.choice(['w1', 'w3'])], 'forger')
            time.sleep(1.0)
        else:
            word.publish(msg)
        time.sleep(rng.uniform(0.05, 0.3))
    if not wait_until(lambda: len(kinds('primary_ignored', before)) >= 3 and kinds('primary_disputed', before),
                      8.0, 0.05):
        sys.exit('seed %d: a passed, empty, disputed or forged word was not refused aloud: %s' % (seed, alarms[-6:]))
    if not any('not the watchdog' in a[3] for a in kinds('primary_ignored', before)):
        sys.exit('seed %d: the forger\'s word was not refused as not the watchdog\'s: %s' % (seed, alarms[-6:]))
    time.sleep(0.5)
    if driven(before) != [B]:
        sys.exit('seed %d: a word that must change nothing changed the driver: %s' % (seed, driven(before)))
    quiet = time.monotonic()
    word.publish(PrimaryBoard(stamp=rospy.Time.now(), board='board_b', nodes=[B], term=2, incarnation='w1'))
    time.sleep(0.5)
    if kinds('primary_ignored', quiet) or kinds('primary_disputed', quiet):
        sys.exit('seed %d: the word in force heard again was alarmed: %s' % (seed, alarms[-2:]))
    word.publish(PrimaryBoard(stamp=rospy.Time.now(), board='board_b', nodes=[B], term=3, incarnation='w1'))
    print('seed %d: a passed term, the same term naming board_a, no node named, another run naming board_a and a '
          'forger\'s word refused aloud; the word in force again silent; board_b drives on' % seed, flush=True)

    # commandManager started again: its configuration names board_a; the latched word names board_b.
    manager.kill()
    manager.wait(10)
    restarted = time.monotonic()
    manager = command_manager()
    if not wait_until(lambda: driven(restarted), 60.0, 0.05):
        sys.exit('seed %d: the restarted commandManager drove nothing: %s' % (seed, open(log_dir + '/command_manager.out').read()[-2000:]))
    time.sleep(rng.uniform(0.5, 1.0))
    wrong = [a for a in kinds('foreign_command', restarted) if B in a[3].split(', not by')[0]]
    if driven(restarted) != [B] or wrong:
        sys.exit('seed %d: started again, commandManager was driven by %s, refused board_b %s'
                 % (seed, driven(restarted), wrong))
    print('seed %d: started again, commandManager waited for the word and took board_b only' % seed, flush=True)
finally:
    for proc in procs:
        proc.kill()
        proc.wait(10)
    core.stop()
print('ok')
'''


def test_the_car_takes_controllerpid_commands_only_from_the_board_the_watchdog_names():
    run_seeded(SCRIPT, home_prefix='aft_command_sources_home_')
